"""``mehs paper``: the paper's Tables 1–5 and Figures 9/10 for every registered method.

:func:`run_paper` trains (or takes checkpoints for) every architecture in the
registry (:data:`mehs.ssr.registry.ARCHITECTURES`) in both settings —
pre-processing on and off, one network each as the paper does — plus its
second learning mode (◇ spectral similarity vs e2e) for Table 1, evaluates
them with the fixed baselines on HDR and LDR input (and on a second, real
dataset for Table 3 when given), times them on a 2048×1024 image from the
dataset (CPU, and CUDA when present), and writes ``paper.md`` and
``paper.html`` with the five tables and the figures.

Layout of ``out``
-----------------
``state.json``            progress (format ``mehs-paper/1``): finished runs and evaluations
``runs/<run>/``           one training run each: ``<arch>-<learning>-pp_<on|off>``
``eval_main/``            ``mehs evaluate`` results on DATASET (HDR and LDR input)
``eval_real/``            the same on ``--real`` (HDR input), when given
``figures/*.png``         Figures 9 (DATASET) and 10 (real)
``paper.md``, ``paper.html``

Resumable: a finished run or evaluation recorded in ``state.json`` is not
repeated; an interrupted run resumes from its ``last.pt``.

Tables (as in the paper): 1 — learning methods (◇ vs e2e, pre-processing on)
on DATASET and the real set; 2 — DATASET, HDR input; 3 — real set, HDR input;
4 — LDR input into the networks trained on HDR; 5 — conversion time.
Each method is scored only in the setting it was trained for; Smits shows "–"
with pre-processing.
"""

from __future__ import annotations

import base64
import html
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mehs.errors import InputError
from mehs.ssr.preprocess import PAPER_PREPROCESSING, Preprocessing

PAPER_FORMAT = "mehs-paper/1"
LEARNING_MARK = {"similarity": "◇", "e2e": "e2e"}
#: ``--quick``: training options per run (tiny nets, few patches): ≤ 10 min on 2 CPU cores.
QUICK = {"epochs": 3, "options": {"patch": 32, "patches_per_image": 4, "batch": 8}}
FULL = {"epochs": 100, "options": {}}


@dataclass(frozen=True)
class Run:
    """One network to train: architecture × learning mode × pre-processing."""

    arch: str
    learning: str
    preprocess: bool
    row: str            # table row (shared by the pp-on and pp-off networks of one method)

    @property
    def name(self) -> str:
        return f"{self.arch}-{self.learning}-pp_{'on' if self.preprocess else 'off'}"


def plan_runs(archs: dict[str, Any]) -> list[Run]:
    """Runs for Tables 1–4: each architecture in its main learning mode (◇ when it has it)
    with pre-processing on and off, and in its other mode with pre-processing on."""
    runs = []
    for name, arch in archs.items():
        modes = [m for m in ("similarity", "e2e") if m in arch.learning]
        main = modes[0]
        runs += [Run(name, main, True, name), Run(name, main, False, name)]
        for other in modes[1:]:
            runs.append(Run(name, other, True, f"{name}-{other}"))
    return runs


def _state(out: Path) -> dict[str, Any]:
    import json

    p = out / "state.json"
    if p.is_file():
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read the progress file ({exc}); delete it to start over", p) from None
        if doc.get("format") != PAPER_FORMAT:
            raise InputError(f"not a 'mehs paper' progress file (format {doc.get('format')!r})", p)
        return doc
    return {"format": PAPER_FORMAT, "runs": {}, "evaluations": {}}


def _save_state(out: Path, state: dict[str, Any]) -> None:
    from mehs.io.atomic import write_json_atomic

    write_json_atomic(out / "state.json", state)


def _pick_preset(arch, quick: bool, preset: str | None) -> str | None:
    if preset is not None:
        return preset
    presets = list(getattr(arch, "presets", {}) or {})
    order = ("tiny", "small") if quick else ("full", "large", "small")
    return next((p for p in order if p in presets), presets[0] if presets else None)


def _train_cli(dataset, out_dir: Path, run: Run, *, preset, preprocessing, input, epochs, device,
               seed, progress, options, learning=None) -> Path:
    """Fallback for architectures without a ``train`` hook: ``mehs train-ssr --arch``."""
    from mehs.cli import main

    argv = ["train-ssr", str(dataset), "--out", str(out_dir), "--arch", run.arch,
            "--mode", run.learning, "--input", input, "--epochs", str(epochs),
            "--device", device, "--seed", str(seed), "--no-onnx"]
    if preset:
        argv += ["--preset", preset]
    if preprocessing is None:
        argv.append("--no-reinhard")
    elif preprocessing.key is not None:
        raise InputError(f"{run.arch}: mehs train-ssr applies Reinhard at a fixed scale; "
                         f"{preprocessing.label()} needs --reinhard-key none")
    else:  # train-ssr's scale s divides: x/s / (1 + x/s)
        argv += ["--reinhard-scale", repr(1.0 / preprocessing.scale)]
    for k, v in (options or {}).items():
        argv += [f"--{k.replace('_', '-')}", str(v)]
    if (out_dir / "last.pt").is_file():
        argv.append("--resume")
    if not progress:
        argv.append("--quiet")
    if main(argv) != 0:
        raise InputError(f"training {run.name} failed (mehs {' '.join(argv)})")
    best = out_dir / "best.pt"
    return best if best.is_file() else out_dir / "last.pt"


def _device(device: str) -> str:
    if device != "auto":
        return device
    try:
        import torch
    except ImportError:
        return "cpu"
    return "cuda" if torch.cuda.is_available() else "cpu"


def _timing_image(dataset, shape: tuple[int, int]) -> np.ndarray:
    """A ``shape`` HDR-RGB image from the dataset: its first scene tiled (mirrored) to size."""
    from mehs.ssr.data import load_pairs

    pairs = load_pairs(dataset)
    rgb = pairs[0].rgb("hdr")
    h, w = shape
    reps = (int(np.ceil(h / rgb.shape[0])), int(np.ceil(w / rgb.shape[1])))
    tile = np.concatenate([rgb, rgb[::-1]], 0)
    tile = np.concatenate([tile, tile[:, ::-1]], 1)
    big = np.tile(tile, (reps[0] // 2 + 1, reps[1] // 2 + 1, 1))[:h, :w]
    return np.ascontiguousarray(big, dtype=np.float32)


def _fig_pngs(results_dir: Path, fig_dir: Path, prefix: str, input: str = "hdr") -> list[tuple[str, Path]]:
    """Scene figures of an evaluation as PNG files (the report's renderer)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mehs.io.atomic import write_bytes_atomic
    from mehs.ssr.report import scene_figures
    from mehs.ssr.results_io import load_results

    doc = load_results(results_dir)
    out = []
    for sid in doc.get("figures", []):
        npz = results_dir / "figures" / f"{sid}.npz"
        if not npz.is_file():
            continue
        for i, (cap, uri) in enumerate(scene_figures(npz, plt)):
            if f"{input.upper()}-RGB" not in cap:
                continue
            path = fig_dir / f"{prefix}_{sid}_{i}.png"
            write_bytes_atomic(path, base64.b64decode(uri.split(",", 1)[1]))
            out.append((cap, path))
    return out


def _table1(main_sum: list, real_sum: list | None, runs: list[Run]) -> tuple:
    from mehs.ssr.results_io import FMT, best_marks

    rows, vals = [], []
    for run in runs:
        if not run.preprocess:
            continue
        look = lambda summ: next((s for s in summ or [] if s["model"] == run.row and  # noqa: E731
                                  s["input"] == "hdr" and s["preprocess"] == "on"), {})
        a, b = look(main_sum), look(real_sum)
        rows.append(f"{run.arch} {LEARNING_MARK[run.learning]}")
        vals.append([a.get("sam"), a.get("mrae")] + ([b.get("sam"), b.get("mrae")] if real_sum else []))
    metrics = ["sam", "mrae"] * (2 if real_sum else 1)
    header = ["Method", "DATASET SAM (°)", "DATASET MRAE"] + (
        ["real SAM (°)", "real MRAE"] if real_sum else [])
    body = [[r] + ["–" if v is None else FMT[m].format(v) for v, m in zip(vs, metrics)]
            for r, vs in zip(rows, vals)]
    return ("Table 1. Learning methods (◇ spectral similarity, e2e end to end), HDR input, "
            "with pre-processing", header, body, best_marks(vals, metrics))


def _paper_block(summary: list, input: str, title: str, rows: Sequence[str]) -> tuple | None:
    from mehs.ssr.results_io import table_blocks

    sub = [s for s in summary if s["input"] == input and s["model"] in rows]
    if not sub:
        return None
    blk = table_blocks(sub)[0]
    # the number of scored images, as the evaluation's own table says it
    return (f"{title} ({max(s['n_images'] for s in sub)} images)",) + tuple(blk[1:])


def _baseline_specs(baselines: Sequence[str]) -> list[tuple[str, str, str]]:
    """``(row, spec for evaluate, spec)`` of each ``--baselines`` entry.

    The row is the name :func:`mehs.ssr.scoring.evaluate` gives the model: the
    ``NAME=`` label, else the loaded model's own name (a fitted ``reg.npz`` is
    the row ``regression``, not ``reg.npz``: the tables pick rows by that name),
    and the spec handed to evaluate carries it as a label so both agree. Loading
    here also makes a misspelt baseline fail before hours of training, not after.
    A bare ``regression`` is fitted by the evaluation (once per setting).
    """
    from mehs.ssr.models import load_model, split_named_spec

    out = []
    for b in baselines:
        label, spec = split_named_spec(str(b).strip())
        if spec.strip().lower() != "regression":
            model = load_model(spec)
            label = label or str(getattr(model, "name", "") or spec)
        label = label or "regression"
        plain = all(c.isalnum() or c in "_-.+" for c in label)
        out.append((label, f"{label}={spec}" if plain else spec, spec))
    return out


def _timing_baseline(spec: str, dataset, seed: int):
    """The model timed for a baseline spec; a bare ``regression`` is fitted on the train
    split here (timing does not depend on the fit, but the model must exist)."""
    from mehs.ssr.models import load_model

    if spec.strip().lower() != "regression":
        return load_model(spec)
    from mehs.ssr.baselines import fit_regression_baseline
    from mehs.ssr.data import load_pairs

    return fit_regression_baseline(load_pairs(dataset, split="train"), seed=seed,
                                   n_samples=20_000)


def run_paper(dataset: str | Path, out: str | Path, *, real: str | Path | None = None,
              quick: bool = False, preset: str | None = None, epochs: int | None = None,
              device: str = "auto", baselines: Sequence[str] = ("smits",),
              checkpoints: dict[str, str] | None = None, archs: Sequence[str] | None = None,
              preprocessing: Preprocessing = PAPER_PREPROCESSING,
              timing_shape: tuple[int, int] = (1024, 2048), seed: int = 0,
              progress: bool = True, log: Callable[[str], None] = print) -> Path:
    """Reproduce the paper's tables and figures on ``dataset``; returns ``out/paper.md``.

    Parameters
    ----------
    dataset
        Training/evaluation dataset (train/val/test splits; scored on test).
    real
        Optional second dataset for Table 3 and Figure 10 (the paper's ME HS set):
        scored only, so every passing scene counts, not just a test split (its
        test split when it is ``dataset`` itself).
    baselines
        Fixed or fitted baselines beside the networks (model specs, ``NAME=SPEC``
        names the row; a bare ``regression`` is fitted on the train split).
    quick
        Tiny presets and few epochs/patches (≤ 10 min on a 2-core CPU for a small set).
    preset, epochs
        Override the preset (default: ``full`` — else the largest — or ``tiny``
        with ``quick``) and the epochs (100, the paper's; 3 with ``quick``).
    checkpoints
        ``run name → checkpoint`` taken instead of training (run names:
        ``<arch>-<learning>-pp_<on|off>``, see :func:`plan_runs`).
    archs
        Restrict to these registered architectures (default: all registered).
    preprocessing
        The Reinhard operator the networks are trained with (default: the
        paper's ``x/(1+x)`` on the data as given).
    """
    from mehs.io.atomic import check_output_dir, make_output_dir
    from mehs.ssr.registry import list_architectures
    from mehs.ssr.scoring import evaluate
    from mehs.ssr.timing import time_models

    out = Path(out)
    check_output_dir(out, inputs=[dataset] + ([real] if real else []))
    registered = list_architectures()
    if archs is not None:
        bad = sorted(set(archs) - set(registered))
        if bad:
            raise InputError(f"architecture(s) {bad} not registered; registered: "
                             f"{sorted(registered) or 'none (install the torch extra)'}")
        registered = {k: v for k, v in registered.items() if k in archs}
    runs = plan_runs(registered)
    checkpoints = dict(checkpoints or {})
    unknown = sorted(set(checkpoints) - {r.name for r in runs})
    if unknown:
        raise InputError(f"--checkpoint names unknown run(s) {unknown}; runs: "
                         f"{[r.name for r in runs]}")
    base_specs = _baseline_specs(baselines)
    make_output_dir(out)
    state = _state(out)
    state.update({"dataset": str(Path(dataset).resolve()),
                  "real": None if real is None else str(Path(real).resolve()), "quick": quick})
    recipe = QUICK if quick else FULL
    n_epochs = int(epochs or recipe["epochs"])
    dev = _device(device)
    steps = len(runs) + 2 + (1 if real else 0) + 1
    step = 0

    def say(msg: str) -> None:
        log(f"[{step}/{steps}] {msg}")

    ckpts: dict[str, str] = {}
    for run in runs:
        step += 1
        done = state["runs"].get(run.name)
        if run.name in checkpoints:
            ckpts[run.name] = str(checkpoints[run.name])
            state["runs"][run.name] = {"checkpoint": ckpts[run.name], "taken": True}
            say(f"{run.name}: using {ckpts[run.name]}")
            continue
        if done and done.get("finished") and Path(done["checkpoint"]).is_file():
            ckpts[run.name] = done["checkpoint"]
            say(f"{run.name}: trained already ({done['checkpoint']})")
            continue
        arch = registered[run.arch]
        pr = _pick_preset(arch, quick, preset)
        say(f"training {run.name} (preset {pr}, {n_epochs} epochs, device {dev})")
        t0 = time.perf_counter()
        kw = dict(preset=pr, learning=run.learning,
                  preprocessing=preprocessing if run.preprocess else None, input="hdr",
                  epochs=n_epochs, device=dev, seed=seed, progress=progress,
                  options=recipe["options"])
        run_dir = out / "runs" / run.name
        ck = arch.train(dataset, run_dir, **kw) if arch.train else _train_cli(dataset, run_dir, run, **kw)
        ckpts[run.name] = str(ck)
        state["runs"][run.name] = {"checkpoint": str(ck), "finished": True, "preset": pr,
                                   "epochs": n_epochs, "device": dev,
                                   "seconds": round(time.perf_counter() - t0, 1)}
        _save_state(out, state)

    model_specs = [f"{r.row}={ckpts[r.name]}" for r in runs] + [e for _, e, _ in base_specs]
    main_rows = [r.row for r in runs if r.row == r.arch] + [row for row, _, _ in base_specs]

    def evaluation(key: str, ds, inputs, folder: Path, split: str | None) -> list:
        nonlocal step
        step += 1
        rec = state["evaluations"].get(key)
        if (rec and rec.get("models") == model_specs and rec.get("split", "auto") == split
                and (folder / "evaluation.json").is_file()):
            say(f"evaluation {key}: done already")
        else:
            say(f"evaluating {len(model_specs)} models on {ds} ({'/'.join(inputs)} input)")
            # a bare 'regression' is fitted with the networks' operator, so the
            # "with pre-processing" column means one operator (paper: "trained in the same way")
            evaluate(ds, model_specs, preprocess="both", inputs=inputs, restore=True,
                     split=split, out=folder, figures=1 if quick else 2, seed=seed,
                     progress=progress, preprocessing=preprocessing)
            state["evaluations"][key] = {"models": model_specs, "split": split, "finished": True}
            _save_state(out, state)
        from mehs.ssr.results_io import load_results

        doc = load_results(folder)
        # the split "auto" scored (test, val, or every scene): the tables say which
        state["evaluations"][key]["scored"] = (doc.get("config") or {}).get("split")
        return doc["summary"]

    main_sum = evaluation("main", dataset, ("hdr", "ldr"), out / "eval_main", "auto")
    # The real set (the paper's ME HS) is only scored, never trained on: every passing scene
    # counts ("We used 82 HDR-HS images to evaluate"), not its test split — unless it is the
    # training dataset itself.
    same = Path(real).resolve() == Path(dataset).resolve() if real else False
    real_sum = (evaluation("real", real, ("hdr",), out / "eval_real", "auto" if same else None)
                if real else None)

    step += 1
    say(f"timing every method on a {timing_shape[1]}×{timing_shape[0]} image from the dataset")
    from mehs.ssr.models import load_model

    timed = []
    for r in runs:
        if r.preprocess and r.row == r.arch:
            m = load_model(ckpts[r.name])
            timed.append((m, r.row))
    timed += [(_timing_baseline(spec, dataset, seed), row) for row, _, spec in base_specs]
    timing = time_models(timed, rgb=_timing_image(dataset, timing_shape), seed=seed,
                         devices=("cpu", "cuda"))
    state["timing"] = timing
    _save_state(out, state)

    step += 1
    say("writing paper.md and paper.html")
    return write_paper(out, runs=runs, main_rows=main_rows, main_sum=main_sum,
                       real_sum=real_sum, timing=timing, state=state)


def _scored(state: dict) -> str:
    """What the main evaluation scored, for Table 2's title: ``split="auto"`` takes the test
    split, else the val split, else every scene (a dataset built without held-out splits)."""
    scored = ((state.get("evaluations") or {}).get("main") or {}).get("scored", "test")
    return {"test": "test split", "val": "val split (no test split)"}.get(
        scored, "every scene: the dataset has no test or val split")


def write_paper(out: Path, *, runs: list[Run], main_rows: list[str], main_sum: list,
                real_sum: list | None, timing: list, state: dict) -> Path:
    """Write ``paper.md`` and ``paper.html`` (tables and figure files); returns ``paper.md``."""
    from mehs.io.atomic import write_text_atomic
    from mehs.ssr.report import _CSS, html_table
    from mehs.ssr.results_io import render_block, timing_block

    no_real = "(no --real dataset given: Table 3 and Figure 10 need the real HDR-HS set)"
    blocks: list[tuple[str, tuple | None, str]] = [
        ("Table 1", _table1(main_sum, real_sum, runs), ""),
        ("Table 2", _paper_block(main_sum, "hdr", f"Table 2. DATASET ({_scored(state)}), "
                                 "HDR-RGB input", main_rows), ""),
        ("Table 3", _paper_block(real_sum or [], "hdr", "Table 3. Real HDR-HS dataset, HDR-RGB "
                                 "input", main_rows), no_real),
        ("Table 4", _paper_block(main_sum, "ldr", "Table 4. LDR-RGB input into the networks "
                                 "trained with HDR images", main_rows),
         "(the dataset has no LDR-RGB images)"),
        ("Table 5", timing_block(timing) if timing else None, ""),
    ]
    if blocks[-1][1] is not None:
        t = blocks[-1][1]
        blocks[-1] = ("Table 5", (f"Table 5. {t[0]} (seconds)",) + tuple(t[1:]), "")
    fig_dir = out / "figures"
    figs9 = _fig_pngs(out / "eval_main", fig_dir, "fig9")
    figs10 = _fig_pngs(out / "eval_real", fig_dir, "fig10") if real_sum is not None else []
    run_lines = [f"- `{r.name}` → row **{r.row}**: {state['runs'].get(r.name, {}).get('checkpoint')}"
                 for r in runs]
    intro = (f"Dataset: `{state.get('dataset')}`; real set: `{state.get('real')}`; "
             f"{'quick' if state.get('quick') else 'full'} run. Each method is scored only in the "
             "setting it was trained for ('–' elsewhere); Smits is not trained, so it has no "
             "pre-processing column.")
    md = ["# SSR: the paper's tables and figures", "", intro, "", "## Runs", "", *run_lines, ""]
    ht = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>mehs paper</title>"
          f"<style>{_CSS}</style></head><body><h1>SSR: the paper's tables and figures</h1>",
          f"<p>{html.escape(intro)}</p><h2>Runs</h2><ul>" +
          "".join(f"<li>{html.escape(line[2:])}</li>" for line in run_lines) + "</ul>"]
    for name, blk, missing in blocks:
        if blk is None:
            md += [f"### {name}", "", missing or "(nothing to show)", ""]
            ht.append(f"<h3>{name}</h3><p>{html.escape(missing or '(nothing to show)')}</p>")
            continue
        md.append(render_block(*blk, "markdown"))
        ht.append(html_table(*blk))
    for label, figs, missing in (("Figure 9 (DATASET)", figs9, "(no figures)"),
                                 ("Figure 10 (real set)", figs10, no_real)):
        md += [f"## {label}", ""]
        ht.append(f"<h2>{label}</h2>")
        if not figs:
            md += [missing, ""]
            ht.append(f"<p>{html.escape(missing)}</p>")
        for cap, path in figs:
            rel = path.relative_to(out).as_posix()
            md += [f"![{cap}]({rel})", "", f"*{cap}*", ""]
            ht.append(f"<figure><img src='{html.escape(rel)}' alt='{html.escape(cap)}'>"
                      f"<figcaption>{html.escape(cap)}</figcaption></figure>")
    ht.append("</body></html>")
    write_text_atomic(out / "paper.html", "\n".join(ht))
    return write_text_atomic(out / "paper.md", "\n".join(md))
