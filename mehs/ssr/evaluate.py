"""Score SSR models on paired HS/RGB scenes: per-image metrics, summaries, paper-style tables.

:func:`evaluate` runs every model under every combination of the paper's
switches — input HDR-RGB / LDR-RGB, Reinhard pre-processing off / on,
luminance restoration on (/ off) — on each scene, computes SAM, MRAE, RMSE and
PSNR per image (:mod:`mehs.ssr.metrics`, dataset masks respected, optional
border crop), and averages them over images.

Results folder (``out``), format ``mehs-evaluation/1``
------------------------------------------------------
``evaluation.json``
    ``{"format", "software_version", "dataset", "split", "config", "models",
    "rows" (one per scene × input × preprocess × restore × model), "summary"
    (one per input × preprocess × restore × model: mean of each metric over the
    images where it is defined, ``n_images``, ``n_undefined``, excluded-pixel
    totals, ``band_mrae``), "timing" (or null), "figures" (scene ids), "skipped"}``
``results.csv`` / ``summary.csv``
    The rows / summary as CSV (per-band lists left out).
``tables.md`` / ``tables.txt``
    The tables (best value per column in **bold** / marked ``*``).
``figures/<scene>.npz``
    For the first ``figures`` scenes: ``preview`` uint8 (H, W, 3) of the input,
    ``sam_<key>`` float16 (H, W) per configuration, ``pixels`` (K, 2),
    ``gt`` (K, B), ``pred_<key>`` (K, B), ``wavelengths``, ``keys`` (JSON list).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from mehs.errors import InputError
from mehs.ssr.data import RGB_INPUTS, PairSet, load_pairs
from mehs.ssr.metrics import HIGHER_IS_BETTER, METRIC_NAMES, image_metrics, sam_map
from mehs.ssr.pipeline import predict

EVALUATION_FORMAT = "mehs-evaluation/1"
PREPROCESS_CHOICES = ("off", "on")
#: Paper Table 5 (CPU i9-11900, 2048×1024) for orientation in the timing table:
#: Smits and the proposed network.
PAPER_SECONDS = {"smits": 0.788, "hdrssr": 16.3}


def config_key(input: str, preprocess: str, restore: bool, model: str) -> str:
    """A file-name-safe key of one configuration, e.g. ``hdr-pp_on-lr_on-smits``."""
    return f"{input}-pp_{preprocess}-lr_{'on' if restore else 'off'}-{model}"


def _as_tuple(v, allowed: Sequence, what: str) -> tuple:
    if isinstance(v, (str, bool)):
        v = [v]
    out = []
    for x in v:
        if isinstance(x, str) and x in ("both", "all"):
            out.extend(allowed)
            continue
        if isinstance(x, bool) and what == "preprocess":
            x = "on" if x else "off"
        if x not in allowed:
            raise InputError(f"{what} must be among {list(allowed)}, got {x!r}")
        out.append(x)
    return tuple(dict.fromkeys(out))


def _resolve_models(models, pairs: PairSet, *, seed: int = 0) -> list[tuple[Any, str, str]]:
    """Load each spec; a bare ``regression`` is fitted on the dataset's train split."""
    from mehs.ssr.models import load_model

    if isinstance(models, str):
        models = [m for m in models.split(",") if m.strip()]
    resolved, names = [], set()
    for spec in models:
        note = ""
        if isinstance(spec, str) and spec.strip().lower() == "regression":
            train_ids = (pairs.splits or {}).get("train") or []
            if pairs.manifest is None or not train_ids:
                raise InputError("the 'regression' baseline needs a train split to fit on; run "
                                 "'mehs train-baseline' and pass the .npz instead", pairs.root)
            from mehs.ssr.baselines import fit_regression_baseline

            model = fit_regression_baseline(load_pairs(pairs.root, split="train"), seed=seed)
            note = f"fitted on the train split ({len(train_ids)} scenes)"
        else:
            model = load_model(spec)
        name = str(getattr(model, "name", spec))
        base, k = name, 2
        while name in names:
            name = f"{base}_{k}"
            k += 1
        names.add(name)
        resolved.append((model, name, note or str(getattr(model, "description", ""))))
    if not resolved:
        raise InputError("no models given")
    return resolved


def native_settings(model) -> tuple[tuple[str, ...], tuple[bool, ...]]:
    """Pre-processing / restoration settings a model can be scored under.

    A model declaring ``preprocessing`` (``"reinhard"`` or ``None``) applies it
    itself, so only that setting is meaningful; one declaring
    ``restores_luminance = True`` is only scored with restoration on.
    """
    pp: tuple[str, ...] = PREPROCESS_CHOICES
    if hasattr(model, "preprocessing"):
        pp = ("on",) if getattr(model, "preprocessing") else ("off",)
    rs: tuple[bool, ...] = (True, False)
    if getattr(model, "restores_luminance", False):
        rs = (True,)
    return pp, rs


def _preview(rgb: np.ndarray) -> np.ndarray:
    """uint8 sRGB preview of linear HDR RGB: median luminance → 0.18, Reinhard on luminance."""
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    pos = lum[lum > 0]
    key = float(np.median(pos)) if pos.size else 1.0
    L = lum * np.float32(0.18 / key)
    scale = np.where(L > 0, 1 / (1 + L), 0).astype(np.float32) * np.float32(0.18 / key)
    x = np.clip(rgb * scale[..., None], 0, 1)
    enc = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(enc * 255).astype(np.uint8)


def _pick_pixels(gt: np.ndarray, valid: np.ndarray, k: int = 4, seed: int = 0) -> np.ndarray:
    """Pixels for the spectra figure: darkest, median, brightest valid, and a random one."""
    lum = gt.sum(-1)
    idx = np.flatnonzero(valid.reshape(-1) & (lum.reshape(-1) > 0))
    if idx.size == 0:
        return np.zeros((0, 2), dtype=int)
    order = idx[np.argsort(lum.reshape(-1)[idx], kind="stable")]
    rng = np.random.default_rng(seed)
    pick = [order[0], order[len(order) // 2], order[-1], rng.choice(order)][:k]
    pick = list(dict.fromkeys(int(p) for p in pick))
    return np.stack(np.unravel_index(pick, gt.shape[:2]), 1)


@dataclass
class EvaluationResult:
    """What :func:`evaluate` computed; ``out`` is the results folder (or None)."""

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    config: dict[str, Any]
    models: list[dict[str, Any]]
    timing: list[dict[str, Any]] | None = None
    skipped: list[dict[str, Any]] = field(default_factory=list)
    figures: list[str] = field(default_factory=list)
    out: Path | None = None

    def tables(self, fmt: str = "markdown", metrics: Sequence[str] = ("sam", "mrae")) -> str:
        return format_tables(self.summary, self.config, fmt=fmt, metrics=metrics,
                             timing=self.timing)


def evaluate(dataset: str | Path | PairSet, models: Iterable | str, *,
             preprocess: Sequence[str] | str = ("off", "on"),
             inputs: Sequence[str] | str = ("hdr",),
             restore: bool | Sequence[bool] | str = True,
             crop: int = 0, split: str | None = None, out: str | Path | None = None,
             figures: int = 2, timing: bool = False,
             timing_shape: tuple[int, int] = (1024, 2048),
             seed: int = 0, progress: bool = False) -> EvaluationResult:
    """Evaluate ``models`` on ``dataset`` under the paper's switches.

    Parameters
    ----------
    dataset
        A dataset folder, a plain folder of pairs, or a :class:`PairSet`.
    models
        Model specs (see :func:`mehs.ssr.models.load_model`) or model objects;
        a comma-separated string is split. A bare ``"regression"`` is fitted on
        the dataset's train split first.
    preprocess
        ``"off"``, ``"on"`` or ``"both"`` (or a sequence of them).
    inputs
        ``"hdr"``, ``"ldr"`` or both.
    restore
        Luminance restoration: ``True``, ``False`` or ``"both"``.
    crop
        Border (pixels) removed on every side before scoring.
    split
        Manifest split to score (``"train"``, ``"val"``, ``"test"``), ``None``
        for every scene, or ``"auto"`` (the test split if there is a non-empty
        one, else every scene).
    out
        Results folder to write (see module notes); ``None`` writes nothing.
    figures
        How many scenes keep per-pixel maps and spectra for the report.
    timing
        Also time each model on a ``timing_shape`` image (paper Table 5).
    """
    if int(crop) < 0:  # image_metrics checks it too, but only once scoring has begun
        raise InputError(f"crop must be ≥ 0, got {crop}")
    if out is not None:
        from mehs.io.atomic import check_output_dir

        check_output_dir(out)  # before the scoring, not after
    pp = _as_tuple(preprocess, PREPROCESS_CHOICES, "preprocess")
    ins = _as_tuple(inputs, RGB_INPUTS, "input")
    if isinstance(restore, str):
        if restore != "both":
            raise InputError(f"restore must be True, False or 'both', got {restore!r}")
        rs: tuple[bool, ...] = (True, False)
    elif isinstance(restore, bool):
        rs = (restore,)
    else:
        rs = tuple(dict.fromkeys(bool(r) for r in restore))
    if isinstance(dataset, PairSet):
        all_pairs = dataset
    else:
        all_pairs = load_pairs(dataset)
    if split == "auto":
        split = "test" if (all_pairs.splits or {}).get("test") else None
    pairs = all_pairs
    if split is not None:
        pairs = load_pairs(all_pairs.root, split=split)
    resolved = _resolve_models(models, all_pairs, seed=seed)

    rows: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    band_acc: dict[str, list] = {}
    fig_ids: list[str] = []
    fig_pending: list[tuple[Path, dict[str, Any]]] = []
    fig_dir = None if out is None else Path(out) / "figures"
    it = pairs
    if progress:
        from tqdm import tqdm
        it = tqdm(pairs, desc="evaluate", unit="scene")
    for i_scene, pair in enumerate(it):
        gt, wl = pair.hs_array()
        valid = pair.valid(gt.shape[:2])
        want_fig = fig_dir is not None and len(fig_ids) < figures
        fig: dict[str, Any] = {}
        if want_fig:
            pix = _pick_pixels(gt, valid, seed=seed + i_scene)
            fig = {"pixels": pix, "gt": gt[pix[:, 0], pix[:, 1]], "wavelengths": wl}
        keys: list[str] = []
        for inp in ins:
            if not pair.has(inp):
                skipped.append({"scene": pair.id, "input": inp, "reason": f"no {inp.upper()}-RGB file"})
                continue
            rgb = pair.rgb(inp)
            if rgb.shape[:2] != gt.shape[:2]:
                raise InputError(f"{inp.upper()}-RGB is {rgb.shape[:2]}, the cube is {gt.shape[:2]}",
                                 pair.hdr_path if inp == "hdr" else pair.ldr_path)
            if want_fig and "preview" not in fig:
                fig["preview"] = _preview(rgb)
            for model, name, _ in resolved:
                pp_ok, rs_ok = native_settings(model)
                for p in pp:
                    if p not in pp_ok:
                        continue
                    for r in rs:
                        if r not in rs_ok:
                            continue
                        t0 = time.perf_counter()
                        pred = predict(model, rgb, preprocess=(p == "on"), restore=r,
                                       wavelengths=wl)
                        dt = time.perf_counter() - t0
                        m = image_metrics(pred, gt, valid=valid, crop=crop)
                        key = config_key(inp, p, r, name)
                        band_acc.setdefault(key, []).append(m.pop("band_mrae"))
                        rows.append({"scene": pair.id, "input": inp, "preprocess": p,
                                     "restore": r, "model": name, **m, "seconds": dt})
                        if want_fig:
                            smap = sam_map(pred, gt)
                            smap[~valid] = np.nan
                            fig[f"sam_{key}"] = smap.astype(np.float16)
                            fig[f"pred_{key}"] = pred[fig["pixels"][:, 0], fig["pixels"][:, 1]]
                            keys.append(key)
        if want_fig and keys:
            fig["keys"] = np.array(json.dumps(keys))
            fig["scene"] = np.array(pair.id)
            # written with the results only once every scene has been scored: a bad
            # scene half-way must not leave a results folder that looks started
            fig_pending.append((fig_dir / f"{pair.id}.npz", fig))
            fig_ids.append(pair.id)

    summary = summarise(rows, band_acc)
    config = {"preprocess": list(pp), "inputs": list(ins), "restore": list(rs), "crop": crop,
              "split": split, "n_scenes": len(pairs), "seed": seed, "notes": []}
    for m, n, _ in resolved:
        pp_ok, rs_ok = native_settings(m)
        if set(pp) - set(pp_ok) or set(rs) - set(rs_ok):
            config["notes"].append(
                f"{n} applies its own pre-processing ({getattr(m, 'preprocessing', None)}) "
                f"{'and luminance restoration ' if rs_ok == (True,) else ''}: scored only with "
                f"pre-processing {'/'.join(pp_ok)}"
                f"{', restoration on' if rs_ok == (True,) else ''}")
    fitted = [n for _, n, d in resolved if d.startswith("fitted on the train split")]
    if fitted and split not in ("test", "val"):
        config["notes"].append(f"{', '.join(fitted)} fitted on the train split and scored on "
                               f"split {split or 'all'}: the scores include training scenes")
    model_info = [{"name": n, "description": d,
                   "wavelengths": np.asarray(m.wavelengths, dtype=float).tolist()}
                  for m, n, d in resolved]
    tim = None
    if timing:
        tim = time_models([(m, n) for m, n, _ in resolved], shape=timing_shape, seed=seed)
    res = EvaluationResult(rows=rows, summary=summary, config=config, models=model_info,
                           timing=tim, skipped=skipped, figures=fig_ids)
    if out is not None:
        for path, fig in fig_pending:
            _write_npz(path, fig)
        res.out = write_results(res, out, dataset=str(all_pairs.root))
    return res


def _write_npz(path: Path, arrays: dict[str, Any]) -> None:
    from mehs.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)


def summarise(rows: list[dict[str, Any]], band_acc: dict[str, list] | None = None) -> list[dict[str, Any]]:
    """Average per-image rows into one entry per configuration (undefined values skipped, never NaN)."""
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r["input"], r["preprocess"], r["restore"], r["model"]), []).append(r)
    out = []
    for (inp, p, rs, name), rs_rows in groups.items():
        s: dict[str, Any] = {"input": inp, "preprocess": p, "restore": rs, "model": name,
                             "n_images": len(rs_rows)}
        for k in METRIC_NAMES:
            vals = [r[k] for r in rs_rows if r.get(k) is not None and np.isfinite(r[k])]
            s[k] = float(np.mean(vals)) if vals else None
            s[f"{k}_undefined"] = len(rs_rows) - len(vals)
        s["sam_excluded"] = int(sum(r.get("sam_excluded", 0) for r in rs_rows))
        s["mrae_excluded"] = int(sum(r.get("mrae_excluded", 0) for r in rs_rows))
        s["seconds_per_image"] = float(np.mean([r["seconds"] for r in rs_rows]))
        key = config_key(inp, p, rs, name)
        if band_acc and key in band_acc:
            bands = np.array([[np.nan if v is None else v for v in b] for b in band_acc[key]],
                             dtype=float)
            cnt = np.isfinite(bands).sum(0)
            with np.errstate(invalid="ignore"):
                mean = np.nansum(bands, 0) / np.maximum(cnt, 1)
            s["band_mrae"] = [float(v) if c else None for v, c in zip(mean, cnt)]
        out.append(s)
    return out


def time_models(models: Sequence, *, shape: tuple[int, int] = (1024, 2048), repeat: int = 1,
                seed: int = 0) -> list[dict[str, Any]]:
    """Conversion time of each model on one synthetic HDR image of ``shape`` (paper Table 5).

    ``models``: model objects or ``(model, name)`` pairs. Each model is warmed up
    on a 16×16 crop, then ``model(rgb)`` is timed ``repeat`` times (best kept)
    and the whole pipeline with luminance restoration once.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    base = rng.gamma(1.0, 1.0, (h // 16 + 1, w // 16 + 1, 3)).astype(np.float32)
    rgb = np.repeat(np.repeat(base, 16, 0), 16, 1)[:h, :w] * np.float32(10.0)
    rgb = np.ascontiguousarray(rgb)
    out = []
    for item in models:
        model, name = item if isinstance(item, tuple) else (item, getattr(item, "name", "model"))
        model(rgb[:16, :16])
        best = np.inf
        for _ in range(max(1, repeat)):
            t0 = time.perf_counter()
            model(rgb)
            best = min(best, time.perf_counter() - t0)
        t0 = time.perf_counter()
        predict(model, rgb, restore=True)
        full = time.perf_counter() - t0
        out.append({"model": name, "shape": [h, w], "seconds": best, "pipeline_seconds": full,
                    "megapixels_per_second": h * w / 1e6 / best,
                    "paper_seconds": PAPER_SECONDS.get(name) if (h, w) == (1024, 2048) else None})
    return out


_FMT = {"sam": "{:.3f}", "mrae": "{:.4f}", "rmse": "{:.4g}", "psnr": "{:.2f}"}
_LABEL = {"sam": "SAM (°)", "mrae": "MRAE", "rmse": "RMSE", "psnr": "PSNR (dB)"}


def _render(title: str, header: list[str], body: list[list[str]], bold: list[list[bool]],
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


def table_blocks(summary: list[dict[str, Any]], *, metrics: Sequence[str] = ("sam", "mrae"),
                 timing: list[dict[str, Any]] | None = None) -> list[tuple]:
    """The paper-style tables as ``(title, header, body, bold)`` blocks (any renderer).

    One table per input × restoration setting: rows are models, columns are
    (pre-processing off / on) × ``metrics``; ``bold[i][j]`` marks the best
    value of column j (ties included, unless every model ties). With ``timing`` a Table-5-like
    conversion-time table is appended.
    """
    blocks = []
    combos = list(dict.fromkeys((s["input"], s["restore"]) for s in summary))
    for inp, rs in combos:
        sub = [s for s in summary if s["input"] == inp and s["restore"] == rs]
        models = list(dict.fromkeys(s["model"] for s in sub))
        pps = [p for p in PREPROCESS_CHOICES if any(s["preprocess"] == p for s in sub)]
        cols = [(p, m) for p in pps for m in metrics]
        header = ["Method"] + [f"{_LABEL[m]} {'w/ ' if p == 'on' else 'w/o '}pre-proc."
                               for p, m in cols]
        look = {(s["model"], s["preprocess"]): s for s in sub}
        vals = [[(look.get((mod, p)) or {}).get(m) for p, m in cols] for mod in models]
        best = []
        for j, (p, m) in enumerate(cols):
            col = [v[j] for v in vals if v[j] is not None]
            best.append(None if not col else (max(col) if HIGHER_IS_BETTER[m] else min(col)))
        body = [[mod] + ["–" if v is None else _FMT[m].format(v) for v, (p, m) in zip(row, cols)]
                for mod, row in zip(models, vals)]
        bold = [[v is not None and best[j] is not None and
                 _FMT[cols[j][1]].format(v) == _FMT[cols[j][1]].format(best[j])
                 for j, v in enumerate(row)] for row in vals]
        for j in range(len(cols)):  # a column where every model ties has no "best"
            marks = [b[j] for b, row in zip(bold, vals) if row[j] is not None]
            if len(marks) > 1 and all(marks):
                for b in bold:
                    b[j] = False
        title = (f"{inp.upper()}-RGB input, luminance restoration {'on' if rs else 'off'}"
                 f" ({max(s['n_images'] for s in sub)} images)")
        blocks.append((title, header, body, bold))
    if timing:
        h, w = timing[0]["shape"]
        header = ["Method", "model (s)", "with restoration (s)", "Mpixel/s", "paper i9-11900 (s)"]
        body = [[t["model"], f"{t['seconds']:.3f}", f"{t['pipeline_seconds']:.3f}",
                 f"{t['megapixels_per_second']:.1f}",
                 "–" if t.get("paper_seconds") is None else f"{t['paper_seconds']:.3f}"]
                for t in timing]
        secs = [t["seconds"] for t in timing]
        bold = [[t["seconds"] == min(secs), False, False, False] for t in timing]
        blocks.append((f"Conversion time on a {w}×{h} image", header, body, bold))
    return blocks


def format_tables(summary: list[dict[str, Any]], config: dict[str, Any] | None = None, *,
                  fmt: str = "markdown", metrics: Sequence[str] = ("sam", "mrae"),
                  timing: list[dict[str, Any]] | None = None) -> str:
    """Paper-style tables (Tables 2–4, and 5 with ``timing``) as Markdown or plain text.

    The best value of each column is **bold** (Markdown) or marked ``*`` (``fmt="text"``).
    See :func:`table_blocks` for the layout.
    """
    if fmt not in ("markdown", "text"):
        raise InputError(f"table format must be 'markdown' or 'text', got {fmt!r}")
    return "\n".join(_render(*b, fmt) for b in table_blocks(summary, metrics=metrics,
                                                             timing=timing))


def write_results(res: EvaluationResult, out: str | Path, *, dataset: str | None = None) -> Path:
    """Write the results folder described in the module notes; returns it."""
    from mehs import __version__
    from mehs.io.atomic import make_output_dir, write_json_atomic, write_text_atomic
    from mehs.ssr.data import write_index_csv

    out = make_output_dir(out)
    doc = {"format": EVALUATION_FORMAT, "software_version": __version__, "dataset": dataset,
           "split": res.config.get("split"), "config": res.config, "models": res.models,
           "rows": res.rows, "summary": res.summary, "timing": res.timing,
           "figures": res.figures, "skipped": res.skipped}
    write_json_atomic(out / "evaluation.json", doc)
    write_index_csv(out / "results.csv", res.rows)
    write_index_csv(out / "summary.csv",
                    [{k: v for k, v in s.items() if k != "band_mrae"} for s in res.summary])
    md = "# SSR evaluation\n\n" + res.tables("markdown") + "\n## All metrics\n\n" + \
        res.tables("markdown", metrics=METRIC_NAMES).replace("### ", "#### ")
    write_text_atomic(out / "tables.md", md)
    write_text_atomic(out / "tables.txt", res.tables("text", metrics=METRIC_NAMES))
    return out


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
