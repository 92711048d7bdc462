"""One scene of the ME HS dataset, as a build worker makes it.

:func:`build_scene` hashes a scene's inputs into its key, and unless the dataset
already holds that key reads the bracket (or HS cube), fuses it, resamples to the
31 bands 400..700 nm, makes the RGB pair and preview and writes them all into
``scenes/.tmp-<id>/``. Committing that folder and the manifest is the main
process's part (:mod:`mehs.dataset.build`); a worker never touches either, so an
interrupted build leaves no half scene listed.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import shutil
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import Any

from mehs import __version__
from mehs.dataset import manifest as mf
from mehs.dataset.parallel import report_stage
from mehs.dataset.portable import portable_provenance, portable_summary
from mehs.errors import MehsError
from mehs.io.atomic import sha256_files
# re-exported: the library API (and tests) import them from here
from mehs.dataset.cube_figures import (dynamic_range_stops, half_float_scale,  # noqa: F401
                                       luminance_low_end, to_31_bands)

# what a scene is built from and keyed by (split from this module); re-exported
from mehs.dataset.scene_task import (BuildParams, SceneTask, _params_for_key,  # noqa: F401
                                     input_files)

TMP_PREFIX = ".tmp-"




def build_scene(task: SceneTask) -> dict[str, Any]:
    """Build one scene into ``scenes/.tmp-<id>/`` (worker entry point; never raises).

    BLAS runs single-threaded here (:mod:`mehs.dataset.threads`): a
    multi-threaded BLAS splits a product differently for different thread
    counts (which follow ``--workers``), and the last bits of ``hs.dat``
    changed with them. The compiled kernels
    parallelise over lines/bands without cross-thread reductions, so with one
    BLAS thread the bytes are the same for any ``--workers`` or ``--scheduler``.

    Returns
    -------
    dict
        ``{"id", "key", "outcome": "skipped"|"built"|"failed", "entry"}`` where
        ``entry`` is the manifest entry (status judged later by the main
        process) and, for failures, ``"error"`` and ``"error_kind"``
        (``"input"`` for a :class:`MehsError`, deterministic and not retried;
        ``"internal"`` otherwise, retried on the next run: an ``OSError`` with its file
        and reason, any other exception with its traceback). Python warnings raised
        while building are not printed: they come back as ``"warnings"`` (also in
        ``entry["provenance"]["run"]["warnings"]``; see
        :mod:`mehs.dataset.scene_warnings`), absent when there were none; paths in
        them name ``scenes/<id>``, where the commit puts the files.
    """
    from mehs.dataset.scene_warnings import captured_warnings, relocate_paths
    from mehs.dataset.threads import one_blas_thread

    with one_blas_thread(), captured_warnings() as caught:
        res = _build_scene(task)
    if caught:
        # a warning names the file it concerns where it was written, scenes/.tmp-<id>/…;
        # the commit renames that folder to scenes/<id>, where the user finds the file
        sid = task.source.scene_id
        relocate_paths(caught, f"{TMP_PREFIX}{sid}", sid)
        # shown by the main process, one line each (raw, from workers, they interleaved)
        res["warnings"] = caught
        if res["entry"] is not None:
            res["entry"]["provenance"]["run"]["warnings"] = caught
    return res


def _build_scene(task: SceneTask) -> dict[str, Any]:
    sid = task.source.scene_id
    run: dict[str, Any] = {"started": _now(), "stage_seconds": {}}
    t_all = time.perf_counter()
    key = None
    hashes: dict[str, str] = {}
    try:
        report_stage(sid, "hash")
        with _timed(run, "hash"):
            files = input_files(task.source)
            hashes = sha256_files(files, threads=_threads())
        key = mf.scene_key(hashes, _params_for_key(task), __version__)
        if task.previous_key == key:
            return {"id": sid, "key": key, "outcome": "skipped", "entry": None}
        tmp = Path(task.dataset) / "scenes" / f"{TMP_PREFIX}{sid}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        # the SHA-256 of files hashed as they were written, by file name
        written: dict[str, str] = {}
        if task.source.kind == "hs":
            quality, extra_prov = _build_from_cube(task, tmp, run, written)
        else:
            quality, extra_prov = _build_from_bracket(task, tmp, run, hashes, written)
        report_stage(sid, "hash outputs")
        with _timed(run, "hash"):
            outs = _outputs(tmp)
            out_files = {name: f"scenes/{sid}/{f.name}" for name, f in outs.items()}
            out_sha = sha256_files({n: f for n, f in outs.items() if f.name not in written},
                                   threads=_threads())
            out_sha = {n: out_sha[n] if n in out_sha else written[f.name]
                       for n, f in outs.items()}
        outcome, error, kind = "built", None, None
    except MehsError as exc:
        outcome, error, kind = "failed", str(exc), "input"
        out_files, out_sha, quality, extra_prov = {}, {}, {}, {}
    except OSError as exc:
        # a file the system would not read or write (permissions, a full disk, a file
        # removed meanwhile): the user's to fix, so a message naming the file, no
        # traceback; retried on the next run, as what failed lies outside the inputs' bytes
        what = exc.strerror or str(exc)
        error = f"{exc.filename}: {what}" if exc.filename else f"{type(exc).__name__}: {what}"
        outcome, kind = "failed", "internal"
        out_files, out_sha, quality, extra_prov = {}, {}, {}, {}
    except Exception as exc:  # noqa: BLE001 - recorded, reported and retried next run
        outcome, error, kind = "failed", f"{type(exc).__name__}: {exc}", "internal"
        out_files, out_sha, quality, extra_prov = {}, {}, {}, {}
        run["traceback"] = traceback.format_exc()
    run["finished"] = _now()
    run["seconds"] = round(time.perf_counter() - t_all, 3)
    inputs, params = portable_provenance(task.source.paths, asdict(task.params), run)
    entry = {
        "id": sid, "status": "fail" if error else "pass", "reasons": [],
        "files": out_files, "sha256": out_sha, "quality": quality,
        "key": key if kind != "internal" else None,
        "provenance": {"kind": task.source.kind, "inputs": inputs,
                       "input_sha256": hashes, "params": params,
                       "response_sha256": task.response_sha256,
                       "software_version": __version__, "run": run, **extra_prov},
    }
    if error:
        entry["error"] = error
    return {"id": sid, "key": key, "outcome": outcome, "entry": entry,
            "error": error, "error_kind": kind}


_OUTPUT_NAMES = {"hs": "hs.hdr", "hs_data": "hs.dat", "hdr_rgb": "hdr_rgb.exr",
                 "ldr_rgb": "ldr_rgb.png", "mask": "mask.png", "preview": "preview.png",
                 "response": "response.json", "fusion": "fusion.json"}


def _outputs(folder: Path) -> dict[str, Path]:
    return {k: folder / n for k, n in _OUTPUT_NAMES.items() if (folder / n).is_file()}


@contextlib.contextmanager
def _timed(run: dict[str, Any], stage: str):
    t0 = time.perf_counter()
    try:
        yield
    finally:
        st = run["stage_seconds"]
        st[stage] = round(st.get(stage, 0.0) + time.perf_counter() - t0, 4)


def _threads() -> int:
    """The merge's thread count (``NUMBA_NUM_THREADS``, ``numba.set_num_threads``), for
    hashing a scene's files side by side."""
    from mehs.synthesis._ranges import thread_count

    return thread_count()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _check_recorded_hashes(root: Path, hashes: dict[str, str]) -> None:
    """Compare input hashes with the SHA-256 that ``scene.json`` recorded per file."""
    import json

    from mehs.errors import FormatError

    doc = json.loads((root / "scene.json").read_text(encoding="utf-8"))
    for exp in doc.get("exposures", []):
        if exp.get("status") != "complete":
            continue
        for rel, digest in (exp.get("files") or {}).items():
            if hashes.get(rel) != digest:
                raise FormatError("SHA-256 does not match scene.json (file altered, "
                                  "truncated or missing)", root / rel)


def _build_from_bracket(task: SceneTask, tmp: Path, run: dict, hashes: dict[str, str],
                        written: dict[str, str]) -> tuple[dict, dict]:
    import numpy as np

    from mehs.io.atomic import write_json_atomic

    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket

    sid = task.source.scene_id
    p = task.params
    report_stage(sid, "read")
    with _timed(run, "read"):
        if task.source.kind == "scene":
            # the inputs were just hashed for the key: check those hashes against the ones
            # recorded at capture instead of letting load_bracket hash 300 MB again
            _check_recorded_hashes(Path(task.source.paths[0]), hashes)
            bracket = load_bracket(task.source.load_arg, verify="size",
                                   allow_partial=p.allow_partial)
        else:
            bracket = load_bracket(task.source.load_arg)
    report_stage(sid, "fuse")
    with _timed(run, "fuse"):
        result = fuse_bracket(bracket, method=p.method, response=p.response or "auto",
                              ghosts=p.ghosts, seed=p.seed, calibration=p.calibration,
                              ghost_bins=p.ghost_bins)
    from mehs.dataset.noisefloor_sat import record_saturation

    # where each exposure saturates (fusion.json): the noise model of what the merge used
    record_saturation(result.summary, bracket, result.response)
    del bracket
    summary = dict(result.summary or {})
    # wall-clock figures belong to the volatile provenance, never to a data file
    for name, sec in (summary.pop("timings", None) or {}).items():
        if name != "total_s":
            run["stage_seconds"][f"fuse.{name.removesuffix('_s')}"] = round(float(sec), 4)
    mask = np.asarray(result.mask, dtype=np.uint8)
    quality = _quality(summary, mask)
    if p.ghosts == "off":
        # nothing was tested: a moving scene's ghosts are unknown, not zero (0.0 passed the rule)
        quality["ghost_fraction"] = None
    quality["n_exposures"] = len(summary["exposure_ratios"])
    chk = (summary.get("response") or {}).get("check") or {}
    quality["response_undetermined"] = bool(summary.get("response_undetermined", False))
    quality["response_uncertainty"] = chk.get("median")
    quality["radiometric_unit"] = summary.get("units")
    cube = result.radiance
    with _timed(run, "write"):
        result.response.save(tmp / "response.json")
        write_json_atomic(tmp / "fusion.json", _jsonable(portable_summary(summary)))
    del result
    from mehs.dataset.noisefloor import model_for_fused

    # the ground truth's own noise, for the pixels it does not resolve (mask bit 8)
    noise = model_for_fused(cube, summary, method=p.resample, fwhm=p.fwhm,
                            calibration=p.calibration)
    _finish_scene(task, cube, mask, tmp, run, quality, written, noise)
    return quality, {}


def _jsonable(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


def _quality(summary: dict, mask) -> dict[str, Any]:
    import numpy as np

    n = max(1, mask.size)
    q = {
        "dynamic_range_stops": summary.get("dynamic_range_stops"),
        "saturated_fraction": float(np.count_nonzero(mask & 1) / n),
        "ghost_fraction": float(np.count_nonzero(mask & 2) / n),
        "invalid_fraction": float(np.count_nonzero(mask & 4) / n),
        "exposure_ratios": summary.get("exposure_ratios"),
    }
    return _jsonable(q)


def _build_from_cube(task: SceneTask, tmp: Path, run: dict,
                     written: dict[str, str]) -> tuple[dict, dict]:
    import numpy as np

    from mehs.io.envi import read_envi

    sid = task.source.scene_id
    report_stage(sid, "read")
    with _timed(run, "read"):
        cube = read_envi(task.source.paths[0], memmap=True)
        data = np.asarray(cube.data, dtype=np.float32)
        bad = ~np.isfinite(data)
        ignore = _ignore_value(cube)
        if ignore is not None:
            # the ENVI marker of a missing sample (a dead pixel, the border of a
            # mosaic) is no radiance: counted as data it entered the RGB and the HS
            bad |= data == np.float32(ignore)
        nonfinite = bad.any(axis=2)
        if bad.any():
            data = np.where(bad, np.float32(0), data)
        cube = cube.with_data(data)
    mask = np.where(nonfinite | ~(data > 0).any(axis=2), np.uint8(4), np.uint8(0))
    # no bracket: exposure, saturation and ghost figures are unknown, not zero
    quality = {**_quality({}, mask), "exposure_ratios": None, "saturated_fraction": None,
               "ghost_fraction": None}
    _finish_scene(task, cube, mask, tmp, run, quality, written)
    return quality, {"source_bands": int(cube.bands)}


def _ignore_value(cube) -> float | None:
    """The header's ``data ignore value`` as a number, or None (a NaN marker is caught as
    non-finite anyway)."""
    from mehs.errors import FormatError

    v = (cube.metadata or {}).get("data ignore value")
    if v in (None, ""):
        return None
    try:
        f = float(str(v).strip())
    except ValueError:
        raise FormatError(f"'data ignore value' {v!r} is not a number", cube.source) from None
    return f if f == f else None


def _finish_scene(task: SceneTask, cube, mask, tmp: Path, run: dict, quality: dict,
                  written: dict[str, str], noise: dict | None = None) -> None:
    """Resample to 31 bands, make the RGB pair and preview, write everything into ``tmp``.

    ``written`` receives ``{file name: SHA-256}`` of the files hashed as they were written
    (the HS cube: ``write_envi`` drops its pages from the cache once written, and a
    second read for the manifest's digest came from the disk).
    ``noise``: the band noise model of the 31-band cube
    (:func:`mehs.dataset.noisefloor.model_for_fused`); pixels it does not resolve get mask
    bit 8 and are counted (``noise_floor_fraction``; ``None`` without a model)."""
    import numpy as np

    from mehs.io.envi import write_envi
    from mehs.io.exr import write_exr_rgb
    from mehs.preview import tonemap, write_png
    from mehs.rgb import WAVELENGTHS_31, hdr_rgb, ldr_rgb, spectra_to_XYZ

    sid = task.source.scene_id
    p = task.params
    report_stage(sid, "resample")
    with _timed(run, "resample"):
        hs = to_31_bands(cube, method=p.resample, fwhm=p.fwhm)  # refuses NaN/Inf
        data = np.ascontiguousarray(hs.data, dtype=np.float32)
    report_stage(sid, "rgb")
    with _timed(run, "rgb"):
        hdr = hdr_rgb(data, WAVELENGTHS_31)
        # the signed luminance of the cube (before the RGB step's clipping) tells the
        # noise floor of a fused cube that keeps its negative estimates
        y = spectra_to_XYZ(data, WAVELENGTHS_31)[..., 1]
        # the scene's range, not its unit, decides the half floats' precision: a dim scene
        # is lifted as a bright one is lowered (precision below the noise is no matter)
        scale = half_float_scale(float(hdr.max()) if hdr.size else 0.0,
                                 luminance_low_end(hdr, mask, signed_luminance=y))
        if scale != 1.0:
            # a power of two commutes exactly with float rounding: HS and RGB stay paired
            data = data * np.float32(scale)
            hdr = hdr * np.float32(scale)
            y = y * np.float32(scale)
        # from the half floats the EXR stores, so that the LDR image and its exposure
        # follow from the dataset's own HDR file (from float32 1 code in ~0.5 % differed)
        ldr, exposure = ldr_rgb(hdr.astype(np.float16).astype(np.float32))
        preview = tonemap(hdr)
    if quality.get("dynamic_range_stops") is None:
        quality["dynamic_range_stops"] = dynamic_range_stops(hdr, mask, signed_luminance=y)
    del y
    from mehs.dataset import noisefloor

    quality.update(noisefloor.screen(data, mask, None if noise is None
                                     else noisefloor.scaled(noise, scale)))
    quality["ldr_exposure"] = float(exposure)
    quality["peak_hdr_rgb"] = float(hdr.max()) if hdr.size else 0.0
    quality["radiance_scale"] = scale
    report_stage(sid, "write")
    with _timed(run, "write"):
        hs = hs.with_data(data, units=cube.units, integration_time_ms=None, source=None,
                          metadata=_scale_header(scale, hs.bands))
        write_envi(tmp / "hs.hdr", hs, dtype=np.float32, interleave="bil", data_ext=".dat",
                   sha256=written)
        write_exr_rgb(tmp / "hdr_rgb.exr", hdr, half=True,
                      header={"mehsRadianceScale": scale})
        write_png(tmp / "ldr_rgb.png", ldr)
        write_png(tmp / "mask.png", mask)
        write_png(tmp / "preview.png", preview)
    from mehs.io.exr import half_underflow_counts

    # recorded, never judged: a scene does not fail for it; a file just written that
    # cannot be read back is an internal error (retried)
    quality.update(half_underflow_counts([tmp / "hdr_rgb.exr"]))


def _scale_header(scale: float, bands: int) -> dict[str, Any]:
    """ENVI header keys stating that ``hs.dat`` holds ``value × scale`` in ``data units``.

    ``mehs radiance scale`` is what mehs's readers divide out. Other readers (SPy, ENVI,
    GDAL) know nothing of it and took the stored numbers for DN/ms or radiance, 2^k off;
    ENVI's own way to say it is a per-band gain (``data units`` = gain · value + offset),
    written whenever the scale is not 1. No reader applies it by itself, but it is
    the documented field a user looks for; ``reflectance scale factor`` (which SPy does
    divide out) would also make mehs's reader divide and break the HS/RGB pair.
    """
    meta: dict[str, Any] = {"mehs radiance scale": repr(scale)}
    if scale != 1.0:
        meta["data gain values"] = [repr(1.0 / scale)] * bands      # exact: a power of two
        meta["data offset values"] = ["0"] * bands
    return meta
