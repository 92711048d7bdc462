"""The whole mehs pipeline on the simulated device, in one call (``mehs demo``).

Stages, each reading what the previous one wrote (so every stage is also what
a user would run by hand):

1. **capture** — for each demo scene, start the simulated Zaber stage and line
   camera on loopback TCP (:class:`mehs.capture.simdevice.SimDevices`), open
   them with the real serial drivers (:class:`~mehs.capture.zaber.ZaberStage`,
   :class:`~mehs.capture.camera.LineCamera`) and capture a bracket with
   auto-exposure (:func:`mehs.capture.session.capture_scene`) into
   ``captures/<id>/``; the simulator's ground truth goes to ``truth/``;
2. **build** — the ME HS set in ``dataset/`` (:func:`mehs.dataset.build.build_dataset`);
3. **train** — the root-polynomial regression baseline on the train split
   (``models/regression.npz``);
4. **evaluate** — Smits 1999, Mallett 2019 and the regression on HDR and LDR
   input, with and without Reinhard pre-processing (``evaluation/``);
5. **reports** — ``dataset/report.html`` and ``evaluation/report.html``;
6. **export** — one scene for spectral rendering (``export/``).

The demo folder holds ``demo.json`` (parameters, per-stage timings and the
summary printed at the end). Re-running with the same parameters reuses what
exists: completed captures are kept (an interrupted one is resumed), built
scenes are skipped by the dataset builder, the rest is recomputed (seconds).

Response curve
--------------
By default the demo works as a lab would with a real camera, once per camera:
it captures a **response ladder** (a grey ramp, ≥ 5 exposures ×4 apart:
``calibration/ladder``), lets ``response="auto"`` decide the curve from it (the
linearity test has the power there that a ×30–×150 HDR bracket lacks, see
:mod:`mehs.synthesis.response_check`) and saves it as ``models/response.json``,
which every scene is fused with. ``known_response=True`` skips the ladder and
hands the builder the simulated sensor's known linear curve
(``models/linear_response.json``).

Radiometric calibration
-----------------------
The simulated camera is calibrated on an integrating sphere with its
certificate (``calibration/sphere``, :func:`calibrate_demo_camera`): the
dataset is in W·sr⁻¹·m⁻²·nm⁻¹, and each cube's median spectral angle and
relative error against the simulator's truth are printed and kept in
``demo.json``.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

from mehs.demo_capture import (DEMO_AUTO_EXPOSURE, calibrate_demo_camera, capture_demo_scene,
                               demo_response_ladder)
from mehs.demo_scenes import demo_pools, demo_scenes
from mehs.errors import InputError

# DEMO_AUTO_EXPOSURE lives in mehs.demo_capture; re-exported (tests import it from here)
__all__ = ["DEMO_AUTO_EXPOSURE", "DEMO_FORMAT", "DEMO_JSON", "DEMO_MODELS", "DEMO_SPLITS",
           "PAPER_SMITS_SAM_ME_HS", "SIZES", "SUBFOLDERS", "format_summary", "run_demo",
           "scene_size", "scene_table", "ssr_table"]

DEMO_FORMAT = "mehs-demo/1"
DEMO_JSON = "demo.json"

#: ``--size`` presets: scene lines = samples (bands are always the 204 Specim IQ bands).
SIZES = {"small": 64, "full": 512}

#: Models scored by the demo (the regression is fitted first, see :func:`run_demo`).
DEMO_MODELS = ("smits", "mallett")

#: Train/val/test fractions: a demo has too few scenes for a validation split, and the
#: regression must not be scored on the scenes it was fitted on.
DEMO_SPLITS = (0.5, 0.0, 0.5)

#: Smits 1999 on the paper's real ME HS scenes (SAM °, HDR input, no pre-processing), printed
#: beside the demo's figure on its natural test scenes (docs/scenes.md explains the gap).
PAPER_SMITS_SAM_ME_HS = 6.392

#: Sub-folders the demo owns inside its output folder (``--force`` removes them).
SUBFOLDERS = ("captures", "calibration", "dataset", "models", "evaluation", "export")


def scene_size(size: str | int) -> int:
    """Lines (= samples) of the demo scenes for ``--size`` (``small``, ``full`` or a number ≥ 8)."""
    if isinstance(size, str) and size in SIZES:
        return SIZES[size]
    try:
        n = int(size)
    except (TypeError, ValueError):
        raise InputError(f"--size must be small, full or a number of pixels, got {size!r}") from None
    if not 8 <= n <= 2048:
        raise InputError(f"--size must be between 8 and 2048 pixels, got {n}")
    return n


# --------------------------------------------------------------------------- the demo
def _check_out(out: Path, params: dict[str, Any], force: bool) -> None:
    marker = out / DEMO_JSON
    if marker.is_file():
        try:
            old = json.loads(marker.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"unreadable demo record ({exc}); delete the folder or use another --out",
                             marker) from None
        if old.get("format") != DEMO_FORMAT:
            raise InputError(f"not a mehs demo record (format {old.get('format')!r})", marker)
        if force:
            for name in SUBFOLDERS:
                shutil.rmtree(out / name, ignore_errors=True)
        elif old.get("params", {}) != params:
            raise InputError(f"this demo folder was made with other parameters "
                             f"({old.get('params')}); use another --out, or --force to start over",
                             out)
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError("exists and is not a mehs demo folder (no demo.json); give another --out",
                         out)


def _fmt(v: Any, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def scene_table(manifest: dict[str, Any], captures: dict[str, dict],
                accuracy: dict[str, dict] | None = None) -> str:
    """Plain-text per-scene summary: exposures, dynamic range, ghosts, saturation,
    radiance accuracy against the simulator's truth (SAM°, median relative error), pass/fail."""
    accuracy = accuracy or {}
    head = f"{'scene':20s} {'exposures (ms)':22s} {'DR stops':>8s} {'ghost %':>8s} " \
           f"{'sat. %':>7s} {'SAM° tr':>7s} {'err % tr':>8s}  status"
    lines = [head, "-" * len(head)]
    for s in manifest["scenes"]:
        q = s.get("quality") or {}
        doc = captures.get(s["id"]) or {}
        times = ", ".join(f"{e['integration_time_ms']:g}" for e in doc.get("exposures", [])
                          if e.get("status") == "complete")
        g, sat = q.get("ghost_fraction"), q.get("saturated_fraction")
        status = s["status"] + (f" ({'; '.join(s['reasons'])})" if s.get("reasons") else "")
        acc = accuracy.get(s["id"]) or {}
        rel = acc.get("rel_error_median")
        lines.append(f"{s['id']:20s} {times:22s} {_fmt(q.get('dynamic_range_stops')):>8s} "
                     f"{_fmt(None if g is None else 100 * g, '.2f'):>8s} "
                     f"{_fmt(None if sat is None else 100 * sat, '.2f'):>7s} "
                     f"{_fmt(acc.get('sam_median_deg'), '.2f'):>7s} "
                     f"{_fmt(None if rel is None else 100 * rel, '.2f'):>8s}  {status}")
    return "\n".join(lines)


def ssr_table(summary: list[dict[str, Any]]) -> str:
    """Plain-text SSR summary: one row per model × input × pre-processing (restoration on)."""
    head = f"{'model':12s} {'input':5s} {'Reinhard':8s} {'SAM °':>7s} {'MRAE':>7s} {'PSNR dB':>8s}"
    lines = [head, "-" * len(head)]
    rows = sorted((s for s in summary if s.get("restore", True)),
                  key=lambda s: (s["input"], s["model"], s["preprocess"]))
    for s in rows:
        lines.append(f"{s['model']:12s} {s['input']:5s} {s['preprocess']:8s} "
                     f"{_fmt(s.get('sam'), '.2f'):>7s} {_fmt(s.get('mrae'), '.4f'):>7s} "
                     f"{_fmt(s.get('psnr'), '.1f'):>8s}")
    return "\n".join(lines)


def run_demo(out: str | Path = "mehs-demo", *, scenes: int = 6, size: str | int = "small",
             seed: int = 0, workers: int | None = None, force: bool = False,
             known_response: bool = False, progress: bool | None = None,
             log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the demo into ``out``; returns the ``demo.json`` document.

    Parameters
    ----------
    out
        Demo folder (created). It may already hold an earlier demo run with the
        same ``size``: completed work is reused.
    scenes
        Number of scenes (≥ 1): the sodium-lamp scene, the moving-cloud scene,
        then natural scenes under other lighting (:func:`demo_scenes`); with the default 6 the
        test split holds 3 scenes.
    size
        ``"small"`` (64×64 pixels × 204 bands), ``"full"`` (512×512×204, the
        Specim IQ format) or a number of pixels per side.
    seed
        Seeds the scenes, the sensor noise, response sampling, the splits and
        the regression's pixel sampling: the same seed gives the same numbers.
    workers
        Scenes built at once by the dataset builder (default: the CPU count).
    force
        Delete the demo's earlier captures and outputs in ``out`` and start over.
    known_response
        Give the builder the simulated sensor's known linear curve instead of
        the curve fused from a captured response ladder (no ladder is captured).
    progress
        Progress bars (default: when stderr is a terminal).
    log
        Called with each progress message (default: print to stdout).

    Returns
    -------
    dict
        ``{"format", "params", "paths", "timings_s", "scenes": [...], "ssr": [...],
        "moving_scene", "lamp_scene", "exported_scene"}``; ``paths`` are absolute.
    """
    from mehs import __version__
    from mehs.io.atomic import write_json_atomic

    say = log or (lambda m: print(m, flush=True))
    bars = sys.stderr.isatty() if progress is None else bool(progress)
    n_pix = scene_size(size)
    specs = demo_scenes(int(scenes))
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    out = Path(out)
    params = {"scenes": len(specs), "size": n_pix, "seed": int(seed),
              "response": "known-linear" if known_response else "auto"}
    _check_out(out, params, force)
    out.mkdir(parents=True, exist_ok=True)
    if not (out / DEMO_JSON).is_file() or force:
        # Written first, so that an interrupted demo is recognised (and resumed) next time.
        write_json_atomic(out / DEMO_JSON, {"format": DEMO_FORMAT, "software_version": __version__,
                                            "params": params, "status": "running"})
    cap_dir, ds_dir, model_dir = out / "captures", out / "dataset", out / "models"
    eval_dir, export_dir = out / "evaluation", out / "export"
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    # 1. capture
    say(f"[1/6] capture: {len(specs)} scenes of {n_pix}×{n_pix} pixels × 204 bands through the "
        f"serial drivers (simulated stage + camera on loopback TCP, auto-exposure)")
    t0 = time.perf_counter()
    captures: dict[str, dict] = {}
    pools = demo_pools(specs, seed, DEMO_SPLITS)
    for i, spec in enumerate(specs):
        captures[spec.scene_id] = capture_demo_scene(spec, cap_dir / spec.scene_id, size=n_pix,
                                                     seed=seed, index=i, progress=bars, log=say,
                                                     pool=pools[spec.scene_id])

    model_dir.mkdir(parents=True, exist_ok=True)
    ladder_curve = None
    if not known_response:
        say(f"  response ladder: grey ramp, >= 5 exposures x4 apart -> {model_dir / 'response.json'}")
        ladder_curve = demo_response_ladder(out / "calibration" / "ladder",
                                            model_dir / "response.json", size=n_pix, seed=seed,
                                            progress=bars, log=say)
    say("  calibration: simulated integrating sphere + certificate -> "
        f"{model_dir / 'calibration.json'} (absolute radiance)")
    cal_path = calibrate_demo_camera(out / "calibration" / "sphere", model_dir / "calibration.json",
                                     size=n_pix, seed=seed, progress=bars, log=say)
    timings["capture"] = time.perf_counter() - t0

    # 2. build
    say(f"[2/6] build: the ME HS set in {ds_dir} (response: "
        f"{'known linear curve' if known_response else 'the ladder curve'}; "
        f"radiometrically calibrated)")
    t0 = time.perf_counter()
    from mehs.dataset.build import build_dataset

    response = ladder_curve
    if known_response:
        from mehs.synthesis.response import ResponseCurve

        response = model_dir / "linear_response.json"
        if not response.is_file():
            ResponseCurve.linear(12).save(response)
    manifest = build_dataset([cap_dir / s.scene_id for s in specs], ds_dir, workers=workers,
                             seed=seed, splits=DEMO_SPLITS, response=response, progress=bars,
                             calibration=cal_path)
    timings["build"] = time.perf_counter() - t0
    from mehs.calibration.accuracy import dataset_truth_accuracy

    accuracy = dataset_truth_accuracy(ds_dir, {s.scene_id: cap_dir / s.scene_id for s in specs})
    if accuracy:
        sams = [a["sam_median_deg"] for a in accuracy.values()]
        rels = [a["rel_error_median"] for a in accuracy.values()]
        say(f"  radiance vs the simulator's truth ({manifest.get('radiance_unit')}): median SAM "
            f"{min(sams):.2f}-{max(sams):.2f} deg, median relative error "
            f"{100 * min(rels):.2f}-{100 * max(rels):.2f} % over {len(accuracy)} scenes")
    n_pass = sum(s["status"] == "pass" for s in manifest["scenes"])
    say(f"  {len(manifest['scenes'])} scenes, {n_pass} pass; splits " +
        ", ".join(f"{k} {len(v)}" for k, v in manifest["splits"].items()))
    # a scene that failed unexpectedly moves the others between splits: say so, since a test
    # scene drawn from the train pool no longer measures generalisation
    built_split = {sid: k for k, v in manifest["splits"].items() for sid in v}
    off_pool = sorted(s.scene_id for s in specs if s.kind == "natural" and
                      s.scene_id in built_split and built_split[s.scene_id] != pools[s.scene_id])
    if off_pool:
        say(f"  note: {', '.join(off_pool)} fell in another split than the pool they were drawn "
            "from (a scene failed unexpectedly)")

    # 3. train the regression baseline
    from mehs.ssr.baselines import fit_regression_baseline
    from mehs.ssr.data import load_pairs

    t0 = time.perf_counter()
    models: list[str] = list(DEMO_MODELS)
    reg_path = model_dir / "regression.npz"
    train_ids = manifest["splits"].get("train") or []
    if train_ids:
        say(f"[3/6] train: root-polynomial regression baseline on the train split "
            f"({', '.join(train_ids)})")
        from mehs.ssr.preprocess import Preprocessing

        # one fit per pre-processing setting, as the paper trains one network per setting
        for path, pp in ((reg_path, None), (reg_path.with_name("regression_pp.npz"), Preprocessing())):
            model = fit_regression_baseline(load_pairs(ds_dir, split="train"), seed=seed,
                                            preprocessing=pp)
            model.info.update({"dataset": str(ds_dir), "split": "train"})
            model.save(path)
            models.append(f"regression={path}")
    else:
        say("[3/6] train: skipped, no scene passed into the train split")
        reg_path.unlink(missing_ok=True)
        reg_path.with_name("regression_pp.npz").unlink(missing_ok=True)
    timings["train"] = time.perf_counter() - t0

    # 4. evaluate
    t0 = time.perf_counter()
    from mehs.ssr.evaluate import evaluate

    res = None
    if n_pass:
        split = "test" if manifest["splits"].get("test") else None
        say(f"[4/6] evaluate: {', '.join(dict.fromkeys(m.split('=')[0] for m in models))} on "
            f"HDR and LDR input, "
            f"Reinhard pre-processing off/on, on the {split or 'whole'} "
            f"{'split' if split else 'set'}")
        res = evaluate(ds_dir, models, preprocess="both", inputs=("hdr", "ldr"), split=split,
                       out=eval_dir, figures=2, seed=seed)
    else:
        say("[4/6] evaluate: skipped, no passing scene")
    timings["evaluate"] = time.perf_counter() - t0

    # 5. reports
    t0 = time.perf_counter()
    say("[5/6] reports: dataset and evaluation HTML")
    from mehs.dataset.report import write_dataset_report

    ds_report = write_dataset_report(ds_dir)
    ev_report = None
    if res is not None:
        from mehs.ssr.report import write_evaluation_report

        ev_report = write_evaluation_report(eval_dir)
    timings["reports"] = time.perf_counter() - t0

    # 6. export one scene for spectral rendering
    t0 = time.perf_counter()
    entries = {s["id"]: s for s in manifest["scenes"]}
    passing = [s.scene_id for s in specs if entries.get(s.scene_id, {}).get("status") == "pass"]
    exported = passing[0] if passing else None
    export_paths: dict[str, str] = {}
    if exported:
        from mehs.export import export_per_wavelength, export_spectral_exr
        from mehs.io.envi import read_envi

        say(f"[6/6] export: {exported} for spectral rendering (31 grayscale EXRs + one spectral EXR)")
        cube = read_envi(ds_dir / entries[exported]["files"]["hs"])
        bands = export_per_wavelength(cube, export_dir / exported, prefix="band")
        spectral = export_spectral_exr(cube, export_dir / f"{exported}_spectral.exr")
        export_paths = {"per_wavelength": str((export_dir / exported).resolve()),
                        "first_band": str(bands[0].resolve()),
                        "spectral_exr": str(spectral.resolve())}
        # spectral image-based lighting of the exported map (only with the render extra)
        from mehs.render.demo import demo_render_step

        render_page = demo_render_step(spectral, export_dir / "render", say)
        if render_page:
            export_paths["render_page"] = render_page
    else:
        say("[6/6] export: skipped, no passing scene")
    timings["export"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all

    scene_rows = []
    for spec in specs:
        e = entries.get(spec.scene_id, {})
        q = e.get("quality") or {}
        doc = captures[spec.scene_id]
        scene_rows.append({
            "id": spec.scene_id, "description": spec.description, "moving": spec.motion,
            "status": e.get("status"), "reasons": e.get("reasons", []),
            "times_ms": [x["integration_time_ms"] for x in doc["exposures"]
                         if x.get("status") == "complete"],
            "dynamic_range_stops": q.get("dynamic_range_stops"),
            "ghost_fraction": q.get("ghost_fraction"),
            "saturated_fraction": q.get("saturated_fraction"),
            "truth_accuracy": accuracy.get(spec.scene_id),
            "split": next((k for k, v in manifest["splits"].items() if spec.scene_id in v), None),
            "pool": pools[spec.scene_id] if spec.kind == "natural" else None})
    ssr = [] if res is None else [
        {k: s.get(k) for k in ("model", "input", "preprocess", "restore", "sam", "mrae", "rmse",
                               "psnr", "n_images")} for s in res.summary]
    doc = {
        "format": DEMO_FORMAT, "software_version": __version__, "params": params,
        "status": "complete", "paths": {"captures": str(cap_dir.resolve()), "dataset": str(ds_dir.resolve()),
                  "dataset_report": str(Path(ds_report).resolve()),
                  "regression_model": str(reg_path.resolve()) if reg_path.is_file() else None,
                  "evaluation": str(eval_dir.resolve()) if res is not None else None,
                  "evaluation_report": str(Path(ev_report).resolve()) if ev_report else None,
                  "export": export_paths or None},
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "radiance_unit": manifest.get("radiance_unit"),
        "calibration": str(cal_path.resolve()),
        "lamp_scene": specs[0].scene_id,
        "moving_scene": next((s.scene_id for s in specs if s.motion), None),
        "exported_scene": exported,
        "off_pool_scenes": off_pool,
        "scenes": scene_rows,
        "ssr": ssr,
        "scene_table": scene_table(manifest, captures, accuracy),
        "ssr_table": ssr_table(ssr) if ssr else None,
    }
    write_json_atomic(out / DEMO_JSON, doc)
    return doc


def format_summary(doc: dict[str, Any]) -> str:
    """The text ``mehs demo`` prints at the end: where everything is, and the two tables."""
    p = doc["paths"]
    rows = [("captures (scene folders)", p["captures"]), ("dataset (ME HS set)", p["dataset"]),
            ("dataset report", p["dataset_report"]), ("regression model", p["regression_model"]),
            ("evaluation results", p["evaluation"]),
            ("evaluation report", p["evaluation_report"]),
            ("spectral EXR export", (p["export"] or {}).get("spectral_exr")),
            ("per-wavelength EXRs", (p["export"] or {}).get("per_wavelength"))]
    width = max(len(k) for k, _ in rows)
    out = ["", "Outputs:"] + [f"  {k:{width}s}  {v}" for k, v in rows if v]
    out += ["", "Scenes:", doc["scene_table"]]
    if doc.get("ssr_table"):
        out += ["", "SSR on the " + ("test split" if any(s["split"] == "test" for s in doc["scenes"])
                                     else "whole set") + " (luminance restoration on; "
                "full tables in evaluation/tables.md):", doc["ssr_table"]]
    smits = next((r for r in doc.get("ssr") or [] if r["model"] == "smits" and r["input"] == "hdr"
                  and r["preprocess"] == "off" and r.get("restore", True)), None)
    if smits and smits.get("sam") is not None:
        out += ["", f"Smits 1999 on the {smits.get('n_images')} natural test scene(s), HDR input: "
                    f"SAM {smits['sam']:.2f}° (the paper, real ME HS scenes: "
                    f"{PAPER_SMITS_SAM_ME_HS:.2f}°; docs/scenes.md on the gap)"]
    t = doc["timings_s"]
    out += ["", "Time: " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items() if k != "total") +
            f"; total {t['total']:.1f} s"]
    return "\n".join(out)
