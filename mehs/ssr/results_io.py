"""Evaluation results: paper-style tables, and the results folder on disk.

Results folder (``out``), format ``mehs-evaluation/1``
------------------------------------------------------
``evaluation.json``
    ``{"format", "software_version", "dataset", "split", "config" (incl. the
    MRAE rule, the pre-processing, the user's pixels and the protocol notes),
    "models" (name, description, ``trained_for``), "rows" (one per scene ×
    input × preprocess × restore × model, incl. ``restore_fallback``),
    "summary" (per configuration: mean/std/median of each metric, excluded and
    fallback counts, ``band_mrae``), "timing" (or null), "figures", "skipped"}``
``results.csv`` / ``summary.csv``
    The rows / summary as CSV (per-band lists left out).
``tables.md`` / ``tables.txt``
    The tables (best value per column in **bold** / marked ``*``), then the
    spread across images and the per-scene tables.
``figures/<scene>.npz``
    ``preview`` uint8 (H, W, 3) of the input, ``sam_<key>`` float16 (H, W) per
    configuration, ``pixels`` (K, 2) (the user's ``--pixels`` first,
    ``n_user_pixels`` of them), ``gt`` (K, B), ``pred_<key>`` (K, B),
    ``wavelengths``, ``keys`` (JSON list).

Tables (:func:`table_blocks`): one per input; rows are models, columns are
(pre-processing on / off) × metrics, as the paper's Tables 2–4; each model's
cells come from the setting it was trained for, "–" elsewhere. A model whose
output allows both and that was also scored in its non-default restoration
setting gets a second row "NAME (restoration off)".
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mehs.errors import InputError
from mehs.ssr.metrics import HIGHER_IS_BETTER, METRIC_NAMES

EVALUATION_FORMAT = "mehs-evaluation/1"
FMT = {"sam": "{:.3f}", "mrae": "{:.4f}", "rmse": "{:.4g}", "psnr": "{:.2f}"}
_LABEL = {"sam": "SAM (°)", "mrae": "MRAE", "rmse": "RMSE", "psnr": "PSNR (dB)"}
_PP_ORDER = ("on", "off")  # the paper's column order: with, then without


def write_npz(path: Path, arrays: dict[str, Any]) -> None:
    from mehs.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


def render_block(title: str, header: list[str], body: list[list[str]], bold: list[list[bool]],
            fmt: str) -> str:
    if fmt == "markdown":
        lines = [f"### {title}", "", "| " + " | ".join(header) + " |",
                 "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
        for row, b in zip(body, bold):
            cells = [row[0]] + [f"**{c}**" if bb else c for c, bb in zip(row[1:], b)]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"
    cells = [header] + [[row[0]] + [c + ("*" if bb else " ") for c, bb in zip(row[1:], b)]
                        for row, b in zip(body, bold)]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = [title, "-" * len(title)]
    for j, r in enumerate(cells):
        lines.append("  ".join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i])
                               for i, c in enumerate(r)))
        if j == 0:
            lines.append("  ".join("-" * wd for wd in widths))
    return "\n".join(lines) + "\n"


def row_label(s: dict[str, Any]) -> str:
    """Table row of a summary entry: the model, plus the restoration setting when it is
    not the model's own (``natural``)."""
    if s.get("natural", bool(s["restore"])) == bool(s["restore"]):
        return s["model"]
    return f"{s['model']} (restoration {'on' if s['restore'] else 'off'})"


def best_marks(vals: list[list[Any]], metrics: list[str]) -> list[list[bool]]:
    """Bold the best value of each column as displayed (ties included), except where
    every value of the column ties: then nothing is best (e.g. PSNR at its 120 dB cap)."""
    marks = [[False] * len(metrics) for _ in vals]
    for j, m in enumerate(metrics):
        col = [(i, v[j]) for i, v in enumerate(vals) if v[j] is not None]
        if not col:
            continue
        best = (max if HIGHER_IS_BETTER[m] else min)(v for _, v in col)
        shown = FMT[m].format(best)
        hit = [FMT[m].format(v) == shown for _, v in col]
        if len(col) > 1 and all(hit):
            continue
        for (i, _), h in zip(col, hit):
            marks[i][j] = h
    return marks


def table_blocks(summary: list[dict[str, Any]], *, metrics: Sequence[str] = ("sam", "mrae"),
                 timing: list[dict[str, Any]] | None = None) -> list[tuple]:
    """The paper-style tables as ``(title, header, body, bold)`` blocks (any renderer)."""
    blocks = []
    for inp in dict.fromkeys(s["input"] for s in summary):
        sub = [s for s in summary if s["input"] == inp]
        labels = list(dict.fromkeys(row_label(s) for s in sub))
        pps = [p for p in _PP_ORDER if any(s["preprocess"] == p for s in sub)]
        cols = [(p, m) for p in pps for m in metrics]
        header = ["Method"] + [f"{_LABEL[m]} {'w/ ' if p == 'on' else 'w/o '}pre-proc."
                               for p, m in cols]
        look = {(row_label(s), s["preprocess"]): s for s in sub}
        vals = [[(look.get((lab, p)) or {}).get(m) for p, m in cols] for lab in labels]
        bold = best_marks(vals, [m for _, m in cols])
        body = [[lab] + ["–" if v is None else FMT[m].format(v) for v, (p, m) in zip(row, cols)]
                for lab, row in zip(labels, vals)]
        title = f"{inp.upper()}-RGB input ({max(s['n_images'] for s in sub)} images)"
        blocks.append((title, header, body, bold))
    if timing:
        blocks.append(timing_block(timing))
    return blocks


def timing_block(timing: list[dict[str, Any]]) -> tuple:
    """Table 5: conversion time (model + its restoration) per method, CPU and CUDA (when
    measured), the paper's i9-11900 / RTX 3090 figures beside it."""
    h, w = timing[0]["shape"]
    header = ["Method", "CPU (s)", "CUDA (s)", "× fastest CPU", "paper CPU (s)", "paper GPU (s)"]
    done = [t["seconds"] for t in timing if t.get("seconds") is not None]
    fastest = min(done) if done else None

    def f(v, spec="{:.3f}"):
        return "–" if v is None else spec.format(v)

    body = [[t["model"] + (f" (CPU: {t['error']})" if t.get("error") else "")
             + (f" (CUDA: {t['cuda_error']})" if t.get("cuda_error") else ""),
             f(t.get("seconds")), f(t.get("cuda_seconds")),
             "–" if t.get("seconds") is None else f(t["seconds"] / fastest, "{:.1f}"),
             f(t.get("paper_seconds")), f(t.get("paper_gpu_seconds"))] for t in timing]
    bold = [[t.get("seconds") is not None and t["seconds"] == fastest] + [False] * 4
            for t in timing]
    return (f"Conversion time on a {w}×{h} image", header, body, bold)


def spread_block(summary: list[dict[str, Any]], metrics: Sequence[str] = ("sam", "mrae")) -> tuple:
    """Spread across images: mean ± std and median per configuration, plus restoration fallbacks."""
    header = ["Method", "input", "pre-proc."] + [f"{_LABEL[m]} {k}" for m in metrics
                                                for k in ("mean ± std", "median")] + \
        ["images", "restoration fallbacks"]
    body, bold = [], []
    for s in summary:
        row = [row_label(s), s["input"].upper(), s["preprocess"]]
        for m in metrics:
            fm = FMT[m]
            row.append("–" if s.get(m) is None else
                       f"{fm.format(s[m])} ± {fm.format(s.get(f'{m}_std') or 0.0)}")
            row.append("–" if s.get(f"{m}_median") is None else fm.format(s[f"{m}_median"]))
        fb = s.get("restore_fallback")
        frac = s.get("restore_fallback_fraction")
        row += [str(s["n_images"]),
                ("n/a" if fb is None and s["restore"] else "–" if fb is None else
                 f"{fb} ({100 * (frac or 0):.1f} %)")]
        body.append(row)
        bold.append([False] * (len(row) - 1))
    return ("Spread across images (sample std); luminance-restoration fallbacks", header,
            body, bold)


def per_scene_blocks(rows: list[dict[str, Any]], summary: list[dict[str, Any]],
                     metric: str = "sam") -> list[tuple]:
    """Per-scene tables, one per input: rows are scenes, columns the configurations."""
    natural = {(s["input"], s["preprocess"], s["restore"], s["model"]): row_label(s)
               for s in summary}
    blocks = []
    for inp in dict.fromkeys(r["input"] for r in rows):
        sub = [r for r in rows if r["input"] == inp]
        cols = list(dict.fromkeys((r["preprocess"], r["restore"], r["model"]) for r in sub))
        cols.sort(key=lambda c: _PP_ORDER.index(c[0]))
        scenes = list(dict.fromkeys(r["scene"] for r in sub))
        look = {(r["scene"], r["preprocess"], r["restore"], r["model"]): r.get(metric) for r in sub}
        header = ["Scene"] + [f"{natural.get((inp, p, rs, m), m)} {'w/' if p == 'on' else 'w/o'} pp"
                              for p, rs, m in cols]
        vals = [[look.get((sc, *c)) for c in cols] for sc in scenes]
        # best per scene: the rows of this table are the columns of best_marks
        bold = [list(r) for r in zip(*best_marks([list(c) for c in zip(*vals)],
                                                 [metric] * len(scenes)))] if vals else []
        body = [[sc] + ["–" if x is None else FMT[metric].format(x) for x in v]
                for sc, v in zip(scenes, vals)]
        blocks.append((f"Per scene, {_LABEL[metric]}, {inp.upper()}-RGB input", header, body, bold))
    return blocks


def format_tables(summary: list[dict[str, Any]], config: dict[str, Any] | None = None, *,
                  fmt: str = "markdown", metrics: Sequence[str] = ("sam", "mrae"),
                  timing: list[dict[str, Any]] | None = None) -> str:
    """Paper-style tables (Tables 2–4, and 5 with ``timing``) as Markdown or plain text.

    The best value of each column is **bold** (Markdown) or marked ``*`` (``fmt="text"``).
    """
    if fmt not in ("markdown", "text"):
        raise InputError(f"table format must be 'markdown' or 'text', got {fmt!r}")
    return "\n".join(render_block(*b, fmt) for b in table_blocks(summary, metrics=metrics,
                                                             timing=timing))


def write_results(res, out: str | Path, *, dataset: str | None = None) -> Path:
    """Write the results folder described in the module notes; returns it."""
    from mehs.io.atomic import make_output_dir
    from mehs.io.lock import OutputLock

    out = make_output_dir(out)
    with OutputLock(out, what="mehs evaluate"):   # two runs never mix their tables
        _write_result_files(res, out, dataset)
    return out


def _write_result_files(res, out: Path, dataset: str | None) -> None:
    from mehs import __version__
    from mehs.io.atomic import write_json_atomic, write_text_atomic
    from mehs.ssr.data import write_index_csv

    doc = {"format": EVALUATION_FORMAT, "software_version": __version__, "dataset": dataset,
           "split": res.config.get("split"), "config": res.config, "models": res.models,
           "rows": res.rows, "summary": res.summary, "timing": res.timing,
           "figures": res.figures, "skipped": res.skipped}
    from mehs.io.atomic import unlink_durable

    # evaluation.json is the commit point (the overwrite check and the report read it):
    # gone before the first file is replaced, written last, so that a run killed half-way
    # leaves no evaluation.json beside another run's tables, and is finished by a re-run
    unlink_durable(out / "evaluation.json")
    write_index_csv(out / "results.csv", res.rows)
    write_index_csv(out / "summary.csv",
                    [{k: v for k, v in s.items() if k != "band_mrae"} for s in res.summary])
    extra = [spread_block(res.summary)] + per_scene_blocks(res.rows, res.summary)
    md = ("# SSR evaluation\n\n" + res.tables("markdown") + "\n## All metrics\n\n" +
          res.tables("markdown", metrics=METRIC_NAMES).replace("### ", "#### ") +
          "\n## Spread and per scene\n\n" +
          "\n".join(render_block(*b, "markdown") for b in extra).replace("### ", "#### "))
    write_text_atomic(out / "tables.md", md)
    write_text_atomic(out / "tables.txt", res.tables("text", metrics=METRIC_NAMES) + "\n" +
                      "\n".join(render_block(*b, "text") for b in extra))
    write_json_atomic(out / "evaluation.json", doc)


def load_results(results_dir: str | Path) -> dict[str, Any]:
    """Read ``evaluation.json`` of a results folder (checking its format)."""
    from mehs.errors import FormatError

    path = Path(results_dir)
    if path.is_dir():
        path = path / "evaluation.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read evaluation results ({exc})", path) from None
    fmt = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
    if fmt != EVALUATION_FORMAT:
        raise FormatError(f"not an evaluation results file (format {fmt!r})", path)
    # a damaged file must fail here, by name, not as a TypeError inside the report
    for key in ("rows", "summary", "skipped"):
        v = doc.get(key, [])
        if not isinstance(v, list) or not all(isinstance(r, dict) for r in v):
            raise FormatError(f"'{key}' must be a list of objects", path)
    return doc


def is_evaluation_folder(path: str | Path) -> bool:
    """True if ``path`` is a results folder written by :func:`evaluate` (for ``mehs report``)."""
    p = Path(path)
    return (p / "evaluation.json").is_file() or (p.is_file() and p.name == "evaluation.json")
