"""The scene folder (``mehs-scene/1``): one bracketed scene as captured by mehs.

Layout::

    <scene>/scene.json                      written atomically after every change
    <scene>/exposures/<k>_<t>ms/            a Specim IQ folder per exposure (k = 0 shortest);
                                            DARKREF at that integration time, WHITEREF at that time
    <scene>/truth/radiance.hdr|.raw         simulated scenes only: ground truth (ENVI float32)

Each exposure record is written with ``"status": "incomplete"`` *before* its
first line is scanned and switched to ``"complete"`` only after its folder has
been renamed into place and hashed, so a crash or ``kill -9`` can never leave
an exposure that claims to be complete. ``files`` maps paths relative to the
scene folder to SHA-256 hex digests.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import FormatError, InputError

SCENE_JSON = "scene.json"
FORMAT = "mehs-scene/1"
#: Stage microsteps per scanned line (simulated geometry and default for sessions).
DEFAULT_PITCH = 64
#: Read-out time per line (ms) used for the frame rate of simulated captures.
READOUT_MS = 0.5
#: Specim IQ default bands {70, 53, 19} (1-based) as 0-based indices.
SPECIM_DEFAULT_BANDS = (69, 52, 18)


def now_iso() -> str:
    """Current UTC time, ISO 8601 with seconds."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def format_time_ms(t: float) -> str:
    """Integration time as written in folder names: ``12.5``, ``0.02``, ``100``."""
    return np.format_float_positional(float(t), trim="-", precision=6)


def exposure_folder_name(k: int, t_ms: float) -> str:
    """``<k>_<t>ms``, e.g. ``0_12.5ms``."""
    return f"{int(k)}_{format_time_ms(t_ms)}ms"


def frame_rate_hz(t_ms: float, readout_ms: float = READOUT_MS) -> float:
    """Line rate of a camera that integrates ``t_ms`` then reads out for ``readout_ms``."""
    return 1000.0 / (float(t_ms) + float(readout_ms))


def software_version() -> str:
    from mehs import __version__
    return f"mehs {__version__}"


def sensor_info(sensor) -> dict[str, Any]:
    """The scalar parameters of a :class:`~mehs.capture.sensor.SensorModel` (JSON-able)."""
    keys = ("gain_dn_per_e", "full_well_e", "read_noise_e", "dark_current_e_per_ms",
            "column_fpn_sigma", "black_level_dn", "bit_depth", "radiance_to_e_per_ms", "seed")
    out = {k: getattr(sensor, k) for k in keys}
    out["response"] = sensor.response if isinstance(sensor.response, str) else "callable"
    return out


def new_scene_doc(scene_id: str, wavelengths, *, seed: int | None = None,
                  device: dict | None = None) -> dict[str, Any]:
    """A fresh ``scene.json`` document with no exposures."""
    return {"format": FORMAT, "scene_id": str(scene_id), "software_version": software_version(),
            "seed": None if seed is None else int(seed),
            "wavelengths": [float(w) for w in np.asarray(wavelengths).reshape(-1)],
            "exposures": [], "white_reference": {}, "device": device or {}, "truth": None,
            "created": now_iso()}


def write_scene_json(scene_dir: str | Path, doc: dict[str, Any]) -> Path:
    """Write ``scene.json`` atomically (temp + rename)."""
    from mehs.io.atomic import write_json_atomic

    doc["updated"] = now_iso()
    return write_json_atomic(Path(scene_dir) / SCENE_JSON, doc)


def read_scene_json(scene_dir: str | Path) -> dict[str, Any]:
    """Read and check ``scene.json`` (format, exposure records)."""
    p = Path(scene_dir) / SCENE_JSON
    if not p.is_file():
        raise InputError("not a scene folder (no scene.json)", Path(scene_dir))
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"scene.json is not valid JSON ({exc})", p) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise FormatError(f"unknown scene format {doc.get('format') if isinstance(doc, dict) else doc!r}"
                          f" (expected {FORMAT})", p)
    if not isinstance(doc.get("exposures"), list):
        raise FormatError("scene.json has no exposure list", p)
    for e in doc["exposures"]:
        if not isinstance(e, dict) or e.get("status") not in ("complete", "incomplete"):
            raise FormatError(f"bad exposure record {e!r}", p)
        check_exposure_record(e, p)
    return doc


def check_exposure_record(e: dict[str, Any], p: Path) -> None:
    """Refuse an exposure record of ``scene.json`` (at ``p``) that would read the wrong data.

    Its ``folder`` must stay inside the scene (a hand-edited ``../other`` would be
    fused with the hashes of this scene's files); a recorded integration time must be
    a positive number (it scales every radiance); ``files`` must map paths to digests.
    """
    rel = e.get("folder")
    which = f"exposure record {e.get('index')!r}"
    if not isinstance(rel, str) or not rel.strip():
        raise FormatError(f"{which} has no 'folder' path", p)
    parts = Path(rel).parts
    if Path(rel).is_absolute() or ".." in parts or (parts and ":" in parts[0]):
        raise FormatError(f"{which}: folder {rel!r} is outside the scene folder", p)
    if "integration_time_ms" in e and e["integration_time_ms"] is not None:
        t = e["integration_time_ms"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (np.isfinite(t) and t > 0):
            raise FormatError(f"{which}: integration_time_ms {t!r} is not a positive number "
                              "of milliseconds", p)
    files = e.get("files")
    if files is not None and not (isinstance(files, dict) and all(
            isinstance(k, str) and isinstance(v, str) for k, v in files.items())):
        raise FormatError(f"{which}: 'files' must map file paths to SHA-256 digests, got "
                          f"{type(files).__name__}", p)


def hash_folder(scene_dir: Path, folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder``, keyed by path relative to ``scene_dir``."""
    from mehs.io.atomic import sha256_file

    return {p.relative_to(scene_dir).as_posix(): sha256_file(p)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def verify_exposure(scene_dir: str | Path, record: dict[str, Any]) -> list[str]:
    """Files of a complete exposure whose SHA-256 no longer matches (or that are missing)."""
    from mehs.io.atomic import sha256_file

    scene_dir = Path(scene_dir)
    bad = []
    for rel, digest in record.get("files", {}).items():
        p = scene_dir / rel
        if not p.is_file() or sha256_file(p) != digest:
            bad.append(rel)
    return bad


def write_exposure(scene_dir: str | Path, k: int, t_ms: float, raw: np.ndarray,
                   dark: np.ndarray | None, white: np.ndarray | None, *, wavelengths,
                   fwhm=None, requested_ms: float | None = None, extra: dict | None = None,
                   started: str | None = None, overwrite: bool = False,
                   metadata: dict[str, str] | None = None) -> dict[str, Any]:
    """Write exposure ``k`` as a Specim IQ folder and return its complete ``scene.json`` record.

    Parameters
    ----------
    raw
        uint16 ``(lines, samples, bands)``.
    dark, white
        References at this time, or ``None``: the lines as read, integer ``(n, samples,
        bands)``, stored exactly as an ``n``-line uint16 slab (as a Specim IQ stores its
        references; readers average the lines), or a float mean line ``(samples, bands)``,
        stored as a 1-line slab rounded to whole DN (±0.5 DN).
    extra
        Fields merged into the record (frame rate, temperature, stage, …).
    """
    from mehs.cube import SpectralCube
    from mehs.io.specim import SpecimCapture, write_specim_folder

    scene_dir = Path(scene_dir)
    name = exposure_folder_name(k, t_ms)
    folder = scene_dir / "exposures" / name
    started = started or now_iso()
    wl = np.asarray(wavelengths, dtype=np.float64)
    date = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
    common = dict(fwhm=fwhm, units="DN", integration_time_ms=float(t_ms), acquisition_date=date,
                  default_bands=SPECIM_DEFAULT_BANDS if wl.size == 204 else None)

    def slab(ref):
        if ref is None:
            return None
        ref = np.asarray(ref)
        if ref.ndim == 3 and np.issubdtype(ref.dtype, np.integer):
            if ref.min(initial=0) < 0 or ref.max(initial=0) > 65535:
                raise InputError(f"reference lines out of uint16 range "
                                 f"[{ref.min()}, {ref.max()}]", folder)
            return SpectralCube(ref.astype(np.uint16), wl, **common)
        if ref.ndim != 2:
            raise InputError(f"a reference is (samples, bands) or integer (lines, samples, "
                             f"bands), got {ref.dtype} {ref.shape}", folder)
        data = np.clip(np.rint(ref.astype(np.float64)), 0, 65535).astype(np.uint16)
        return SpectralCube(data[None], wl, **common)

    meta = {"integration_time": format_time_ms(t_ms), "datetime": date,
            "software": software_version(), "exposure_index": str(int(k))}
    meta.update(metadata or {})
    cap = SpecimCapture(capture_id=name, root=None, raw=SpectralCube(raw, wl, **common),
                        darkref=slab(dark), whiteref=slab(white), metadata=meta)
    write_specim_folder(folder, cap, overwrite=overwrite)
    rec = {"index": int(k), "folder": f"exposures/{name}",
           "requested_integration_time_ms": float(requested_ms if requested_ms is not None else t_ms),
           "integration_time_ms": float(t_ms), "status": "complete",
           "frame_rate_hz": frame_rate_hz(t_ms), "temperature_c": None,
           "started": started, "finished": now_iso(),
           "saturation_fraction": None,
           "stage": {"start_position": None, "end_position": None, "warnings": []},
           "lines": int(raw.shape[0])}
    rec.update(extra or {})
    rec["status"] = "complete"
    rec["files"] = hash_folder(scene_dir, folder)
    return rec


def refuse_new_capture_into(out: str | Path) -> None:
    """Raise :class:`InputError` when a new capture may not start in ``out``: a file there,
    a scene captured already (``--resume`` finishes it), or a folder inside a raw capture.

    ``mehs capture`` asks before it takes the folder's lock (even a lock file would change
    a raw capture); :func:`mehs.capture.session.capture_scene` asks again for library callers.
    """
    from mehs.io.atomic import raw_capture_containing

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("output folder exists and is not a folder", out)
    cap = raw_capture_containing(out)
    if cap is not None and cap == out.resolve():
        raise InputError("a scene was already captured here; use --resume to finish it "
                         "(raw captures are never overwritten)", out)
    if cap is not None:
        raise InputError(f"output lies inside the raw capture {cap}; raw captures are never "
                         "written into — choose an output outside it", out)
