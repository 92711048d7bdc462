"""HTML report of an SSR evaluation (the paper's Tables 2–5 and Figures 9/10).

:func:`write_evaluation_report` reads a results folder written by
:func:`mehs.ssr.scoring.evaluate` and writes one self-contained HTML file
(figures embedded as base64 PNG, no network access needed) with

- the protocol (each model's trained-input declaration, the MRAE element
  rule, the pre-processing), the notes (incl. luminance-restoration fallbacks);
- the summary tables (SAM/MRAE, then all four metrics; best value in bold),
  the spread across images (mean ± std, median) and the per-scene table, and
  the conversion-time table when timing was measured;
- per scene kept for figures, per input: the input preview, the method with
  the lowest SAM at each pixel (each method at its best setting per pixel,
  as the paper's Figure 10), the SAM map of every configuration, and the
  spectra at the user's ``--pixels`` and at selected pixels;
- the per-wavelength MRAE of every configuration, on a log axis.

Any combination of models and settings renders: figures only use the
configurations a scene actually has.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.ssr.metrics import METRIC_NAMES
from mehs.ssr.results_io import (load_results, per_scene_blocks, row_label, spread_block,
                                 table_blocks, timing_block)
from mehs.ssr.scoring import parse_key

_CSS = """body{font-family:sans-serif;margin:2em;max-width:1400px}
table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #bbb;padding:3px 8px;text-align:right}
th:first-child,td:first-child{text-align:left}caption{font-weight:bold;text-align:left;padding:4px 0}
img{max-width:100%}figure{margin:1em 0}figcaption{color:#444;font-size:90%}"""


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def html_table(title: str, header: list[str], body: list[list[str]], bold: list[list[bool]]) -> str:
    e = html.escape
    rows = ["<tr>" + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>"]
    for r, b in zip(body, bold):
        cells = [f"<td>{e(r[0])}</td>"] + [f"<td>{'<b>' + e(c) + '</b>' if bb else e(c)}</td>"
                                           for c, bb in zip(r[1:], b)]
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><caption>{e(title)}</caption>{''.join(rows)}</table>"


def _key_label(key: str, keys: list[str]) -> str:
    """``model w/ pp`` — plus the restoration setting when the model has both in ``keys``."""
    inp, pp, lr, m = parse_key(key)
    both = len({parse_key(k)[2] for k in keys if parse_key(k)[3] == m}) > 1
    return f"{m} {'w/' if pp == 'on' else 'w/o'} pp" + (f", restoration {lr}" if both else "")


def _best_method_map(sams: dict[str, np.ndarray], keys: list[str]) -> tuple[list[str], np.ndarray]:
    """Per pixel, the model with the lowest SAM, each model at its best setting there.

    Returns ``(models, index map)`` with NaN where no model has an angle.
    """
    models = list(dict.fromkeys(parse_key(k)[3] for k in keys))
    per_model = []
    for m in models:
        st = np.stack([sams[k] for k in keys if parse_key(k)[3] == m])
        st = np.where(np.isfinite(st), st, np.inf).min(0)
        per_model.append(st)
    stack = np.stack(per_model)
    finite = np.isfinite(stack).any(0)
    best = np.argmin(stack, 0).astype(float)
    best[~finite] = np.nan
    return models, best


def scene_figures(npz_path: Path, plt) -> list[tuple[str, str]]:
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    out = []
    with np.load(npz_path, allow_pickle=False) as z:
        keys = json.loads(str(z["keys"]))
        scene = str(z["scene"])
        preview = z["preview"]
        wl = z["wavelengths"]
        pix = z["pixels"]
        gt = z["gt"]
        n_user = int(z["n_user_pixels"]) if "n_user_pixels" in z.files else 0
        sams = {k: z[f"sam_{k}"].astype(np.float32) for k in keys}
        preds = {k: z[f"pred_{k}"] for k in keys}
    for inp in dict.fromkeys(parse_key(k)[0] for k in keys):
        ks = [k for k in keys if parse_key(k)[0] == inp]
        models, best = _best_method_map(sams, ks)
        vmax = max(float(np.nanpercentile(sams[k], 99)) if np.isfinite(sams[k]).any() else 1.0
                   for k in ks) or 1.0
        ncol = min(4, 2 + len(ks))
        nrow = int(np.ceil((2 + len(ks)) / ncol))
        fig, axes = plt.subplots(nrow, ncol, figsize=(2.8 * ncol, 2.9 * nrow), squeeze=False)
        axf = axes.ravel()
        axf[0].imshow(preview)
        axf[0].set_title(f"input {inp.upper()}-RGB", fontsize=8)
        cmap = ListedColormap(list(plt.get_cmap("tab20").colors)[:max(len(models), 1)])
        axf[1].imshow(best, cmap=cmap, vmin=-0.5, vmax=len(models) - 0.5, interpolation="nearest")
        fin = np.isfinite(best)
        shares = [np.mean(best[fin] == j) * 100 if fin.any() else 0.0 for j in range(len(models))]
        axf[1].set_title("lowest SAM per pixel", fontsize=8)
        axf[1].legend(handles=[Patch(color=cmap(j), label=f"{m} {sh:.0f}%")
                               for j, (m, sh) in enumerate(zip(models, shares))],
                      fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2,
                      frameon=False)
        im = None
        for j, k in enumerate(ks):
            im = axf[2 + j].imshow(sams[k], cmap="magma", vmin=0, vmax=vmax)
            axf[2 + j].set_title(f"SAM° {_key_label(k, ks)}", fontsize=7)
        if im is not None:
            fig.colorbar(im, ax=axf[1 + len(ks)], fraction=0.046)
        for ax in axf:
            ax.set_xticks([])
            ax.set_yticks([])
        for ax in axf[2 + len(ks):]:
            ax.axis("off")
        fig.suptitle(f"{scene}, {inp.upper()}-RGB input", fontsize=9)
        out.append((f"{scene} — {inp.upper()}-RGB: input, method with the lowest SAM per pixel "
                    f"(each at its best setting; share of pixels), SAM maps (degrees; masked "
                    f"pixels blank)", _png(fig)))
        if len(pix):
            n = len(pix)
            fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 2.8), squeeze=False)
            for c in range(n):
                ax = axes[0, c]
                ax.plot(wl, gt[c], "k-", lw=2.2, label="ground truth")
                for k in ks:
                    ax.plot(wl, preds[k][c], "--" if parse_key(k)[1] == "on" else "-", lw=1,
                            label=_key_label(k, ks))
                who = "chosen" if c < n_user else "auto"
                ax.set_title(f"({who}) row {pix[c][0]}, col {pix[c][1]}", fontsize=8)
                ax.set_xlabel("nm", fontsize=8)
                ax.tick_params(labelsize=7)
            axes[0, -1].legend(fontsize=6, loc="best")
            out.append((f"{scene} — spectra, {inp.upper()}-RGB input: {n_user} chosen pixel(s) "
                        f"(--pixels), then the darkest, median, brightest and a random valid "
                        f"pixel", _png(fig)))
    return out


def _band_figure(summary: list[dict[str, Any]], wl: np.ndarray, plt) -> list[tuple[str, str]]:
    out = []
    for inp in dict.fromkeys(s["input"] for s in summary):
        sub = [s for s in summary if s["input"] == inp and s.get("band_mrae")]
        if not sub:
            continue
        fig, ax = plt.subplots(figsize=(7, 3.5))
        for s in sub:
            y = np.array([np.nan if v is None else v for v in s["band_mrae"]], dtype=float)
            y[~(y > 0)] = np.nan  # a log axis has no place for 0
            x = wl if wl.size == y.size else np.arange(y.size)
            ax.plot(x, y, "--" if s["preprocess"] == "on" else "-",
                    label=f"{row_label(s)} ({'w/' if s['preprocess'] == 'on' else 'w/o'} pp)")
        ax.set_yscale("log")
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("MRAE (log)")
        ax.legend(fontsize=7)
        ax.set_title(f"{inp.upper()}-RGB input", fontsize=9)
        out.append((f"Per-wavelength MRAE, {inp.upper()}-RGB input (log axis)", _png(fig)))
    return out


def _protocol_html(doc: dict[str, Any]) -> list[str]:
    e = html.escape
    cfg = doc.get("config", {})
    rule = cfg.get("mrae_rule") or {"threshold": 0.0, "relative": False, "band_range": None}
    br = rule.get("band_range")
    pp = cfg.get("preprocessing") or {}
    parts = [f"<p>MRAE element rule: ground truth &gt; {rule.get('threshold', 0):g}"
             f"{' × the image maximum' if rule.get('relative') else ''}; bands "
             f"{'all' if not br else f'{br[0]:g}–{br[1]:g} nm'}. Pre-processing for "
             f"fixed baselines (when asked) and regressions fitted here: "
             f"{e(json.dumps(pp))}; fixed baselines with pre-processing: "
             f"{'yes' if cfg.get('fixed_preprocess') else 'no'}.</p>"]
    parts.append("<h2>Models and what they were trained for</h2><ul>" + "".join(
        f"<li><b>{e(m['name'])}</b>: {e(m.get('trained_for_label') or 'not recorded')} — "
        f"{e(m.get('description') or '')}</li>" for m in doc.get("models", [])) + "</ul>")
    return parts


def write_evaluation_report(results_dir: str | Path, out_html: str | Path | None = None) -> Path:
    """Write the HTML report of a results folder; returns the HTML path.

    ``out_html`` defaults to ``<results_dir>/report.html``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mehs.io.atomic import write_text_atomic

    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise InputError("no such evaluation results folder", results_dir)
    doc = load_results(results_dir)
    out_html = Path(out_html) if out_html is not None else results_dir / "report.html"
    e = html.escape
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>SSR evaluation</title>"
             f"<style>{_CSS}</style></head><body><h1>SSR evaluation</h1>"]
    cfg = doc.get("config", {})
    parts.append(f"<p>Dataset: <code>{e(str(doc.get('dataset')))}</code>; split: "
                 f"{e(str(doc.get('split')))}; scenes: {cfg.get('n_scenes')}; border crop: "
                 f"{cfg.get('crop')} px; mehs {e(str(doc.get('software_version')))}.</p>")
    for note in cfg.get("notes", []):
        parts.append(f"<p><b>Note:</b> {e(note)}</p>")
    parts.append("<p>SAM in degrees (zero-norm pixels excluded and counted), MRAE over "
                 "the elements the rule below admits, RMSE in the data's units, PSNR with "
                 "peak = the ground truth's maximum per image; per image, then averaged. "
                 "Masked pixels (saturated, ghost, invalid) are not scored. Each model is "
                 "scored only in the setting it was trained for; '–' elsewhere.</p>")
    parts += _protocol_html(doc)
    summary = doc.get("summary", [])
    rows = doc.get("rows", [])
    parts.append("<h2>SAM and MRAE</h2>")
    parts += [html_table(*b) for b in table_blocks(summary)]
    if doc.get("timing"):
        parts.append(html_table(*timing_block(doc["timing"])))
    parts.append("<h2>All metrics</h2>")
    parts += [html_table(*b) for b in table_blocks(summary, metrics=METRIC_NAMES)]
    if summary:
        parts.append("<h2>Spread across images and per scene</h2>")
        parts.append(html_table(*spread_block(summary)))
        parts += [html_table(*b) for m in ("sam", "mrae") for b in per_scene_blocks(rows, summary, m)]
    excl = [s for s in summary if s.get("sam_excluded") or s.get("mrae_excluded")]
    if excl:
        parts.append("<p>Excluded from SAM / MRAE (zero-norm pixels / elements outside the "
                     "MRAE rule): " +
                     "; ".join(f"{e(s['model'])} {s['input']} pp {s['preprocess']}: "
                               f"{s['sam_excluded']} / {s['mrae_excluded']}" for s in excl) + "</p>")
    unres = [s for s in summary if s.get("unresolved_pixels") or s.get("mrae_floor_excluded")]
    if unres:
        # the scores above leave out ground truth buried in its own noise: say how much
        parts.append("<p>Ground truth not resolved above its own noise, not scored (pixels "
                     "of mask bit 8 / further elements left out of MRAE, y ≤ 10σ): " +
                     "; ".join(f"{e(s['model'])} {s['input']} pp {s['preprocess']}: "
                               f"{s.get('unresolved_pixels') or 0} / "
                               f"{s.get('mrae_floor_excluded') or 0}" for s in unres) +
                     ". <code>mehs evaluate --score-unresolved</code> scores them.</p>")
    if doc.get("skipped"):
        parts.append("<p>Skipped: " + e("; ".join(f"{s['scene']} {s['input']}: {s['reason']}"
                                                   for s in doc["skipped"])) + "</p>")
    figs: list[tuple[str, str]] = []
    wl = None
    for sid in doc.get("figures", []):
        npz = results_dir / "figures" / f"{sid}.npz"
        if npz.is_file():
            with np.load(npz, allow_pickle=False) as z:
                wl = z["wavelengths"]
            figs += scene_figures(npz, plt)
    if wl is None and doc.get("models"):
        wl = np.asarray(doc["models"][0]["wavelengths"])
    parts.append("<h2>Figures</h2>")
    for cap, uri in figs + _band_figure(summary, np.asarray(wl if wl is not None else []), plt):
        parts.append(f"<figure><img src='{uri}' alt='{e(cap)}'><figcaption>{e(cap)}"
                     "</figcaption></figure>")
    parts.append("</body></html>")
    write_text_atomic(out_html, "\n".join(parts))
    return out_html
