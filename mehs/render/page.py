"""``index.html`` of a render comparison: the renders, their ×5 differences and numbers.

Self-contained apart from the PNGs beside it (relative links), no scripts, no network.
"""

from __future__ import annotations

import html
from pathlib import Path

from mehs.io.atomic import write_text_atomic

_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:.3em .6em;
text-align:right}th{background:#f4f4f4}td.l,th.l{text-align:left}
.grid{display:flex;flex-wrap:wrap;gap:1em}.cell{text-align:center;font-size:.9em}
.cell img{image-rendering:pixelated;width:256px;border:1px solid #888;display:block}
"""


def _fmt(v, spec=".3f") -> str:
    return "–" if v is None else format(v, spec)


def write_page(out: Path, doc: dict) -> Path:
    """Write ``out/index.html`` for a ``render.json`` document; return its path."""
    e = html.escape
    s = doc["settings"]
    rows, cells = [], []
    for r in doc["results"]:
        rows.append(
            f"<tr><td class=l>{e(r['name'])}</td><td class=l>{e(r['description'])}</td>"
            f"<td>{_fmt(r.get('mean_delta_E2000'))}</td><td>{_fmt(r.get('relative_error'), '.4f')}</td>"
            f"<td>{_fmt(r.get('mean_sam_deg'), '.2f')}</td><td>{r['seconds']:.1f}</td></tr>")
        diff = (f"<img src=\"{e(r['diff_png'])}\" alt=\"{e(r['name'])} difference ×5\">"
                f"difference ×{doc['difference_gain']:g}" if "diff_png" in r else "reference")
        cells.append(f"<div class=cell><img src=\"{e(r['png'])}\" alt=\"{e(r['name'])}\">"
                     f"<b>{e(r['name'])}</b><br>{diff}</div>")
    body = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>mehs render: {e(s['material'])}</title>
<style>{_CSS}</style></head><body>
<h1>Spectral image-based lighting</h1>
<p>Object <code>{e(str(s['object']))}</code>, material <code>{e(s['material'])}</code>,
{s['width']}×{s['height']} pixels, {s['spp']} samples per pixel, seed {s['seed']};
map <code>{e(str(doc['map']['source']))}</code> ({doc['map']['shape'][0]}×{doc['map']['shape'][1]},
{len(doc['map']['wavelengths_nm'])} bands). Reference: the spectral render with the HS map.
Images share the reference's exposure ({doc['exposure']:.4g}); differences are
|render − reference| × {doc['difference_gain']:g}.</p>
<table><tr><th class=l>render</th><th class=l>lighting</th><th>mean ΔE2000</th>
<th>relative error</th><th>SAM (°)</th><th>time (s)</th></tr>
{''.join(rows)}</table>
<div class=grid>{''.join(cells)}
<div class=cell><img src="{e(doc['files']['env_rgb.png'])}" alt="environment map">
environment map (pseudo-HDR-RGB)</div></div>
<p>ΔE2000 on CIELAB relative to the reference's 99th-percentile luminance; relative error
Σ|render − reference| / Σ|reference| over pixels and channels; SAM: mean spectral angle to
the reference spectra (spectral renders only).</p>
</body></html>
"""
    return write_text_atomic(out / "index.html", body)
