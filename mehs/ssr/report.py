"""HTML report of an SSR evaluation (the paper's Tables 2–5 and Figures).

:func:`write_evaluation_report` reads a results folder written by
:func:`mehs.ssr.evaluate.evaluate` and writes one self-contained HTML file
(figures embedded as base64 PNG, no network access needed) with

- the summary tables (SAM/MRAE, then all four metrics; best value in bold) and
  the conversion-time table when timing was measured;
- per scene kept for figures: the input RGB preview, a map of the method with
  the lowest SAM at each pixel, the per-pixel SAM map of each method, and the
  spectra at selected pixels (ground truth vs each method);
- the per-wavelength MRAE of each method and setting.
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
from mehs.ssr.evaluate import load_results, table_blocks
from mehs.ssr.metrics import METRIC_NAMES

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


def _html_table(title: str, header: list[str], body: list[list[str]], bold: list[list[bool]]) -> str:
    e = html.escape
    rows = ["<tr>" + "".join(f"<th>{e(h)}</th>" for h in header) + "</tr>"]
    for r, b in zip(body, bold):
        cells = [f"<td>{e(r[0])}</td>"] + [f"<td>{'<b>' + e(c) + '</b>' if bb else e(c)}</td>"
                                           for c, bb in zip(r[1:], b)]
        rows.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><caption>{e(title)}</caption>{''.join(rows)}</table>"


def _parse_key(key: str) -> tuple[str, str, str, str]:
    inp, pp, lr, model = key.split("-", 3)
    return inp, pp.split("_", 1)[1], lr.split("_", 1)[1], model


def _scene_figures(npz_path: Path, plt) -> list[tuple[str, str]]:
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
        sams = {k: z[f"sam_{k}"].astype(np.float32) for k in keys}
        preds = {k: z[f"pred_{k}"] for k in keys}
    groups: dict[tuple, list[str]] = {}
    for k in keys:
        inp, pp, lr, model = _parse_key(k)
        groups.setdefault((inp, lr), []).append(k)
    for (inp, lr), ks in groups.items():
        pps = list(dict.fromkeys(_parse_key(k)[1] for k in ks))
        models = list(dict.fromkeys(_parse_key(k)[3] for k in ks))
        vmax = max(float(np.nanpercentile(sams[k], 99)) if np.isfinite(sams[k]).any() else 1.0
                   for k in ks) or 1.0
        ncol = 2 + len(models)
        fig, axes = plt.subplots(len(pps), ncol, figsize=(2.6 * ncol, 3.0 * len(pps)),
                                 squeeze=False)
        cmap = ListedColormap(plt.get_cmap("tab10").colors[:max(len(models), 1)])
        for i, pp in enumerate(pps):
            axes[i, 0].imshow(preview)
            axes[i, 0].set_title(f"input {inp.upper()}-RGB", fontsize=8)
            stack = np.stack([sams[f"{inp}-pp_{pp}-lr_{lr}-{m}"] for m in models])
            finite = np.isfinite(stack).any(0)
            best = np.where(finite, np.nanargmin(np.where(np.isfinite(stack), stack, np.inf), 0),
                            -1).astype(float)
            best[~finite] = np.nan
            axes[i, 1].imshow(best, cmap=cmap, vmin=-0.5, vmax=len(models) - 0.5,
                              interpolation="nearest")
            shares = [np.mean(best[finite] == j) * 100 for j in range(len(models))]
            axes[i, 1].set_title(f"lowest SAM, pre-proc. {pp}", fontsize=8)
            axes[i, 1].legend(handles=[Patch(color=cmap(j), label=f"{m} {sh:.0f}%")
                                       for j, (m, sh) in enumerate(zip(models, shares))],
                              fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.02),
                              ncol=2, frameon=False)
            for j, m in enumerate(models):
                im = axes[i, 2 + j].imshow(stack[j], cmap="magma", vmin=0, vmax=vmax)
                axes[i, 2 + j].set_title(f"SAM° {m}, pre-proc. {pp}", fontsize=8)
            fig.colorbar(im, ax=axes[i, -1], fraction=0.046)
            for ax in axes[i]:
                ax.set_xticks([])
                ax.set_yticks([])
        fig.suptitle(f"{scene}: luminance restoration {lr}", fontsize=9)
        out.append((f"{scene} — {inp.upper()}-RGB, restoration {lr}: input, method with the "
                    f"lowest SAM per pixel (share of pixels), SAM maps (degrees; masked pixels "
                    f"blank)", _png(fig)))
        if len(pix):
            n = len(pix)
            fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 2.8), squeeze=False)
            for c in range(n):
                ax = axes[0, c]
                ax.plot(wl, gt[c], "k-", lw=2.2, label="ground truth")
                for k in ks:
                    _, pp, _, m = _parse_key(k)
                    ax.plot(wl, preds[k][c], "--" if pp == "on" else "-", lw=1,
                            label=f"{m} (pre-proc. {pp})")
                ax.set_title(f"pixel (row {pix[c][0]}, col {pix[c][1]})", fontsize=8)
                ax.set_xlabel("nm", fontsize=8)
                ax.tick_params(labelsize=7)
            axes[0, -1].legend(fontsize=6, loc="best")
            out.append((f"{scene} — spectra at selected pixels (darkest, median, brightest, "
                        f"random), {inp.upper()}-RGB, restoration {lr}", _png(fig)))
    return out


def _band_figure(summary: list[dict[str, Any]], wl: np.ndarray, plt) -> list[tuple[str, str]]:
    out = []
    combos = list(dict.fromkeys((s["input"], s["restore"]) for s in summary))
    for inp, rs in combos:
        sub = [s for s in summary if s["input"] == inp and s["restore"] == rs and s.get("band_mrae")]
        if not sub:
            continue
        fig, ax = plt.subplots(figsize=(7, 3.5))
        for s in sub:
            y = np.array([np.nan if v is None else v for v in s["band_mrae"]])
            x = wl if wl.size == y.size else np.arange(y.size)
            ax.plot(x, y, "--" if s["preprocess"] == "on" else "-",
                    label=f"{s['model']} (pre-proc. {s['preprocess']})")
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("MRAE")
        ax.legend(fontsize=7)
        ax.set_title(f"{inp.upper()}-RGB, restoration {'on' if rs else 'off'}", fontsize=9)
        out.append((f"Per-wavelength MRAE, {inp.upper()}-RGB input, luminance restoration "
                    f"{'on' if rs else 'off'}", _png(fig)))
    return out


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
                 "elements with ground truth &gt; 0, RMSE in the data's units, PSNR with "
                 "peak = the ground truth's maximum per image; per image, then averaged. "
                 "Masked pixels (saturated, ghost, invalid) are not scored.</p>")
    parts.append("<h2>Models</h2><ul>" + "".join(
        f"<li><b>{e(m['name'])}</b>: {e(m.get('description') or '')}</li>"
        for m in doc.get("models", [])) + "</ul>")
    summary = doc.get("summary", [])
    parts.append("<h2>SAM and MRAE</h2>")
    parts += [_html_table(*b) for b in table_blocks(summary, timing=doc.get("timing"))]
    parts.append("<h2>All metrics</h2>")
    parts += [_html_table(*b) for b in table_blocks(summary, metrics=METRIC_NAMES)]
    excl = [s for s in summary if s.get("sam_excluded") or s.get("mrae_excluded")]
    if excl:
        parts.append("<p>Excluded from SAM / MRAE (zero-norm pixels / elements with y ≤ 0): " +
                     "; ".join(f"{e(s['model'])} {s['input']} pp {s['preprocess']}: "
                               f"{s['sam_excluded']} / {s['mrae_excluded']}" for s in excl) + "</p>")
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
            figs += _scene_figures(npz, plt)
    if wl is None and doc.get("models"):
        wl = np.asarray(doc["models"][0]["wavelengths"])
    parts.append("<h2>Figures</h2>")
    for cap, uri in figs + _band_figure(summary, np.asarray(wl if wl is not None else []), plt):
        parts.append(f"<figure><img src='{uri}' alt='{e(cap)}'><figcaption>{e(cap)}"
                     "</figcaption></figure>")
    parts.append("</body></html>")
    write_text_atomic(out_html, "\n".join(parts))
    return out_html
