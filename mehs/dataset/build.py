"""Build the ME HS dataset: bracketed scenes → HDR-HS + HDR-RGB/LDR-RGB pairs.

Per scene (one task, run in a worker): hash the inputs → scene key; if the
dataset already holds this key, skip. Otherwise read the bracket
(:func:`mehs.synthesis.bracket.load_bracket`), fuse it (dark subtraction,
response recovery or a given curve, merge, ghost detection —
:func:`mehs.synthesis.fuse.fuse_bracket`), resample to the 31 bands
400..700 nm (:func:`mehs.synthesis.resample.resample_cube`), make the
pseudo-HDR-RGB and LDR-RGB images (:func:`mehs.rgb.hdr_rgb`,
:func:`mehs.rgb.ldr_rgb`) and a tone-mapped preview, and write them into
``scenes/.tmp-<id>/``. The main process then renames that folder to
``scenes/<id>/`` and rewrites the manifest atomically (the commit point), so
an interrupted build leaves no half scene listed and re-running finishes it.
Python warnings a worker raises are kept with its scene (``provenance.run.warnings``) and
printed by the main process after the build, one line per warning naming the scene
(:mod:`mehs.dataset.scene_warnings`); an interrupted build prints those of the scenes
it committed on its way out.
The worker's part is :mod:`mehs.dataset.scene_build`; this module is the main
process's (scene list, lock, scheduling, commits, splits, manifest).

Outputs are deterministic: no timestamps in data files; wall-clock times live
only in the manifest's volatile ``scenes[].provenance.run`` subtree.

Files of one scene (relative to the dataset folder, ``files`` in the manifest)::

    scenes/<id>/hs.hdr + hs.dat   ENVI float32 (lines, samples, 31) bil, 400..700 nm
    scenes/<id>/hdr_rgb.exr       half-float linear sRGB, channels R, G, B
    scenes/<id>/ldr_rgb.png       8-bit sRGB-encoded LDR-RGB
    scenes/<id>/mask.png          uint8: 0 valid, 1 saturated in all, 2 ghost, 4 other invalid
    scenes/<id>/preview.png       tone-mapped 8-bit preview (report thumbnails)
    scenes/<id>/response.json     the response curve used (bracket scenes)
    scenes/<id>/fusion.json       the fusion summary (bracket scenes)
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Callable, Iterable

from mehs import __version__
from mehs.dataset import manifest as mf
from mehs.dataset.parallel import default_workers, run_tasks
from mehs.dataset.quality import QualityRules, judge
from mehs.dataset.reuse import (moved_between_splits, outputs_intact, record_output_stat,
                                remove_stale_temp_files, split_of)
from mehs.dataset.scene_build import (TMP_PREFIX, BuildParams, SceneTask, build_scene,
                                      dynamic_range_stops, half_float_scale, input_files,
                                      to_31_bands)
from mehs.dataset.scene_list import SceneSource, collect_hs_cubes, collect_scenes
from mehs.dataset.scene_warnings import describe
from mehs.dataset.splits import make_splits, parse_fractions, write_split_files
from mehs.errors import InputError
from mehs.io.atomic import sha256_file

LOCK_NAME = ".mehs-build.lock"
GHOST_MODES = ("detect", "deghost", "off")
OLD_PREFIX = ".old-"

# the worker side lives in scene_build; these names stay importable from here
__all__ = ["BuildParams", "SceneTask", "build_dataset", "build_from_hs", "build_scene",
           "dynamic_range_stops", "half_float_scale", "input_files", "to_31_bands",
           "GHOST_MODES", "LOCK_NAME"]


# ---------------------------------------------------------------- main side

def _Lock(dataset: Path):
    """The dataset's build lock: two builds never write one dataset."""
    from mehs.io.lock import OutputLock

    return OutputLock(dataset, name=LOCK_NAME, what="mehs build")


def _rgb_block() -> dict[str, str]:
    import mehs.rgb as rgb

    rule = (f"mehs.rgb.ldr_rgb: {rgb.LDR_EXPOSURE_RULE}; then clip to [0, 1], sRGB OETF, "
            "rint(255 v); the exposure of each scene is quality.ldr_exposure")
    return {"xyz_scale": "1/sum(ybar)", "ldr_exposure_rule": rule,
            "matrix": "XYZ->linear sRGB (D65), IEC 61966-2-1 / paper, negatives clipped",
            "cmfs": rgb.CMFS_NAME}


def build_dataset(scenes: Iterable[str | Path | SceneSource], out: str | Path, *,
                  workers: int | None = None, force: bool = False,
                  response: str | Path | None = None, method: str = "poisson",
                  ghosts: str = "detect", seed: int = 0,
                  splits: str | tuple[float, float, float] = (0.7, 0.15, 0.15),
                  rules: QualityRules | None = None, resample: str = "gaussian",
                  fwhm: float = 10.0, scheduler: Any = None, progress: bool = True,
                  on_commit: Callable[[dict], None] | None = None,
                  calibration: str | Path | None = None, verify: bool = False,
                  allow_partial: bool = False,
                  ghost_bins: int | str = "auto") -> dict[str, Any]:
    """Build (or resume, or extend) the dataset folder ``out``.

    Parameters
    ----------
    scenes
        Scene folders, folders of scene folders, CSV/TOML scene lists (see
        :mod:`mehs.dataset.scene_list`) or :class:`SceneSource` objects.
    out
        The dataset folder (created if needed). Scenes already in its manifest
        but not given now are kept.
    workers
        Scenes built at once (default: the CPU count); also the bound on the
        scenes held in memory.
    force
        Rebuild scenes even when their key is unchanged.
    response
        A response-curve file to use instead of recovering one per scene.
    method, ghosts, ghost_bins, seed, resample, fwhm
        See :class:`BuildParams`; ``seed`` also seeds the splits.
    splits
        Train/val/test fractions over the passing scenes.
    rules
        Pass/fail thresholds (:class:`~mehs.dataset.quality.QualityRules`).
    calibration
        A calibration file (``mehs calibrate``) applied to every scene: the
        dataset is in its unit (recorded in the manifest); without one it is
        in DN/ms and says so (``radiance_unit``, report, ``mehs info``).
    scheduler
        A Dask scheduler address or ``distributed.Client`` to run scenes on.
    progress
        Show a tqdm bar (scenes done/total, ETA, current stage per scene).
    on_commit
        Called with each scene entry right after the manifest holding it was
        written (progress hooks, tests).
    verify
        Hash every output of a scene before reusing it; by default only outputs
        whose size or mtime changed since they were written are hashed. A scene
        whose outputs no longer match their recorded SHA-256 is rebuilt.
    allow_partial
        Fuse scenes whose ``scene.json`` marks an exposure incomplete from the
        complete ones (otherwise such a scene fails, naming the exposure).

    Returns
    -------
    dict
        The final manifest.
    """
    raw = [scenes] if isinstance(scenes, (str, Path)) else list(scenes)
    paths = [s for s in raw if not isinstance(s, SceneSource)]
    srcs = [s for s in raw if isinstance(s, SceneSource)] + (collect_scenes(paths) if paths else [])
    if not srcs:
        raise InputError("no scenes to build")
    from mehs.synthesis.merge import MERGE_METHODS

    if method not in MERGE_METHODS:  # refuse before any scene is attempted
        raise InputError(f"unknown merge method {method!r}; use one of {sorted(MERGE_METHODS)}")
    if ghosts not in GHOST_MODES:
        raise InputError(f"ghosts must be one of {list(GHOST_MODES)}, got {ghosts!r}")
    rules = rules or QualityRules()
    fractions = parse_fractions(splits)
    params = BuildParams(method=method, response=str(Path(response).resolve()) if response else None,
                         ghosts=ghosts, seed=int(seed), resample=resample, fwhm=float(fwhm),
                         calibration=str(Path(calibration).resolve()) if calibration else None,
                         allow_partial=bool(allow_partial), ghost_bins=ghost_bins)
    radiometric = {"radiance_unit": "DN/ms (uncalibrated)", "calibration": None}
    if calibration:
        from mehs.calibration import Calibration

        cal = Calibration.load(calibration)   # a bad file is one error, not one per scene
        radiometric = {"radiance_unit": cal.unit, "calibration": cal.summary()}
    response_sha = None
    if response:
        if not Path(response).is_file():
            raise InputError("response curve file not found", response)
        from mehs.synthesis.response import ResponseCurve

        # an unreadable curve is one error, not one per scene
        loaded = ResponseCurve.load(response)
        if params.ghost_bins not in ("auto", 1) and params.ghosts != "off" \
                and not loaded.is_linear:
            from mehs.synthesis.merge_types import refuse_bins_for_curve

            refuse_bins_for_curve(params.ghost_bins, "this response curve", loaded.method,
                                  response)
        response_sha = sha256_file(response)
    return _run_build(srcs, Path(out), params, response_sha, workers=workers, force=force,
                      fractions=fractions, rules=rules, scheduler=scheduler,
                      progress=progress, on_commit=on_commit, radiometric=radiometric,
                      verify=verify)


def build_from_hs(cubes: Iterable[str | Path], out: str | Path, *,
                  workers: int | None = None, force: bool = False, seed: int = 0,
                  splits: str | tuple[float, float, float] = (0.7, 0.15, 0.15),
                  rules: QualityRules | None = None, resample: str = "gaussian",
                  fwhm: float = 10.0, scheduler: Any = None, progress: bool = True,
                  on_commit: Callable[[dict], None] | None = None,
                  verify: bool = False) -> dict[str, Any]:
    """Make a paired set from existing ENVI HS cubes (any band set covering 400..700 nm).

    Each cube (``.hdr`` file, or every ``*.hdr`` of a folder; id = file stem) is
    resampled to the 31 bands and paired with its pseudo-HDR-RGB and LDR-RGB
    images exactly as bracket scenes are. There is no bracket, so saturation,
    ghost and exposure figures are ``None`` and the dynamic-range rule is off
    unless ``rules`` sets it. See :func:`build_dataset` for the other parameters.
    """
    srcs = collect_hs_cubes(list(cubes) if not isinstance(cubes, (str, Path)) else [cubes])
    rules = rules or QualityRules(min_dynamic_range_stops=0.0)
    params = BuildParams(seed=int(seed), resample=resample, fwhm=float(fwhm))
    return _run_build(srcs, Path(out), params, None, workers=workers, force=force,
                      fractions=parse_fractions(splits), rules=rules, scheduler=scheduler,
                      progress=progress, on_commit=on_commit, verify=verify)


def _run_build(srcs, dataset: Path, params, response_sha, *, workers, force, fractions,
               rules, scheduler, progress, on_commit,
               radiometric: dict | None = None, verify=False) -> dict[str, Any]:
    from mehs.io.atomic import make_output_dir

    created = not dataset.exists()
    make_output_dir(dataset, inputs=[p for s in srcs for p in s.paths if s.kind != "hs"])
    warned: list[dict] = []   # results with warnings, of scenes committed (or skipped)
    try:
        return _run_build_locked(srcs, dataset, params, response_sha, created, warned,
                                 workers=workers,
                                 force=force, fractions=fractions, rules=rules,
                                 scheduler=scheduler, progress=progress, on_commit=on_commit,
                                 radiometric=radiometric, verify=verify)
    finally:
        # an interrupted build (Ctrl-C, a failure that stops it) still shows the warnings
        # of the scenes it committed; a complete one has printed them already (emptied)
        _print_warnings(warned)


def _print_warnings(warned: list[dict]) -> None:
    """Print the scenes' warnings, by scene id (the same lines whatever the workers'
    order), once: the list is emptied."""
    for res in sorted(warned, key=lambda r: r["id"]):
        for w in res["warnings"]:
            print(f"mehs build: scene {res['id']}: {describe(w)}", file=sys.stderr)
    warned.clear()


def _run_build_locked(srcs, dataset: Path, params, response_sha, created: bool,
                      warned: list[dict], *,
                      workers, force, fractions, rules, scheduler, progress, on_commit,
                      radiometric, verify) -> dict[str, Any]:
    import json

    from mehs.rgb import WAVELENGTHS_31

    scenes_dir = dataset / "scenes"
    with _drop_if_empty_on_error(dataset, created), _Lock(dataset):
        scenes_dir.mkdir(exist_ok=True)
        for d in scenes_dir.iterdir():  # leftovers of an interrupted build
            if d.name.startswith((TMP_PREFIX, OLD_PREFIX)):
                shutil.rmtree(d, ignore_errors=True)
        remove_stale_temp_files(dataset)
        if (dataset / mf.MANIFEST_NAME).exists():
            manifest = mf.read_manifest(dataset)
            if manifest.get("wavelengths") != [float(w) for w in WAVELENGTHS_31]:
                raise InputError("existing manifest has other wavelengths than 400..700/10",
                                 dataset / mf.MANIFEST_NAME)
        else:
            manifest = mf.new_manifest(software_version=__version__,
                                       wavelengths=WAVELENGTHS_31, rgb=_rgb_block())
        before = json.dumps(manifest, sort_keys=True, default=str)
        old_split = split_of(manifest)
        manifest["software_version"] = __version__
        manifest["quality_rules"] = rules.to_dict()
        if radiometric is not None:
            manifest.update(radiometric)
        entries = mf.scene_map(manifest)
        for e in entries.values():  # rules may have changed since the last build
            e["status"], e["reasons"] = judge(e.get("quality") or {}, rules, e.get("error"))
        tasks = []
        for s in srcs:
            old = entries.get(s.scene_id)
            prev = None
            if (old and not force and old.get("key")
                    and outputs_intact(dataset, old, full=verify)):
                prev = old["key"]
            tasks.append((s.scene_id, SceneTask(s, str(dataset), params, prev, response_sha)))

        def refresh() -> None:
            manifest["scenes"] = sorted(entries.values(), key=lambda e: e["id"])
            passing = [e["id"] for e in manifest["scenes"] if e["status"] == "pass"]
            manifest["splits"] = make_splits(passing, fractions, params.seed)

        def commit() -> None:
            refresh()
            write_split_files(dataset, manifest["splits"])
            mf.write_manifest(dataset, manifest)

        n_workers = workers or default_workers()
        stages: dict[str, str] = {}
        finished: set[str] = set()
        bar = _progress_bar(len(tasks), progress)

        def show_stages() -> None:
            bar.set_postfix_str(" ".join(f"{k}:{v}" for k, v in stages.items())[:60],
                                refresh=False)

        def on_stage(tid: str, stage: str) -> None:
            if tid not in finished:  # stage messages can arrive after the result
                stages[tid] = stage
                show_stages()
        failures = []
        # scenes the manifest on disk lists (their folders must not change while listed)
        listed = {e["id"] for e in manifest["scenes"]}
        try:
            for res in run_tasks(build_scene, tasks, workers=n_workers,
                                 scheduler=scheduler, on_stage=on_stage):
                sid = res["id"]
                finished.add(sid)
                stages.pop(sid, None)
                show_stages()
                if res["outcome"] == "skipped":
                    if res.get("warnings"):
                        warned.append(res)
                    bar.update(1)
                    continue
                entry = res["entry"]
                if sid in listed:
                    # the manifest on disk lists this scene's folder, which _place replaces
                    # file by file: unlist it first, so that a kill in between leaves a
                    # manifest without the scene, never one naming missing or other files
                    entries.pop(sid, None)
                    commit()
                    listed.discard(sid)
                _place(scenes_dir, sid, built=res["outcome"] == "built")
                record_output_stat(dataset, entry)
                entry["status"], entry["reasons"] = judge(entry["quality"], rules,
                                                          entry.get("error"))
                entries[sid] = entry
                commit()
                if res.get("warnings"):   # committed: printed even if the build stops now
                    warned.append(res)
                if res["outcome"] == "failed":
                    failures.append(res)
                if on_commit is not None:
                    on_commit(entry)
                bar.update(1)
        finally:
            bar.close()
        refresh()  # rules or splits may have changed even when every scene was skipped
        if (json.dumps(manifest, sort_keys=True, default=str) != before
                or not (dataset / "splits").is_dir()):
            commit()
    moved = moved_between_splits(old_split, split_of(manifest))
    if moved:
        # cuts follow the number of passing scenes: adding scenes shifts them; say so, since
        # a model trained on the old train split may now be scored on its own scenes
        print(f"mehs build: {len(moved)} existing scene(s) changed split (the split cuts "
              f"follow the number of passing scenes): "
              + ", ".join(f"{sid} {a} → {b}" for sid, a, b in moved), file=sys.stderr)
    _print_warnings(warned)   # after the progress bar, before the failures
    for res in failures:
        tb = res["entry"]["provenance"]["run"].get("traceback")
        print(f"mehs build: scene {res['id']} failed: {res['error']}", file=sys.stderr)
        if tb:
            print(tb, file=sys.stderr)
    return manifest


@contextlib.contextmanager
def _drop_if_empty_on_error(folder: Path, created: bool):
    """On an error, remove ``folder`` if this build created it and it holds no file yet.

    E.g. an unreachable ``--scheduler`` must not leave an empty dataset folder
    that a later build (or a user) would take for a started one.
    """
    try:
        yield
    except BaseException:
        if created and not any(p.is_file() for p in folder.rglob("*")):
            shutil.rmtree(folder, ignore_errors=True)
        raise


def _place(scenes_dir: Path, sid: str, *, built: bool) -> None:
    """Move ``.tmp-<id>`` to ``<id>`` (replacing an older build), or drop stale outputs."""
    final = scenes_dir / sid
    tmp = scenes_dir / f"{TMP_PREFIX}{sid}"
    old = scenes_dir / f"{OLD_PREFIX}{sid}"
    if final.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    if built:
        os.replace(tmp, final)
    else:
        shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(old, ignore_errors=True)


def _progress_bar(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="scene", desc="mehs build", disable=not enabled,
                dynamic_ncols=True)
