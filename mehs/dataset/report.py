"""Static HTML report of a dataset folder (opens offline, no server).

``write_dataset_report(DATASET)`` writes ``DATASET/report.html`` and its images
in ``DATASET/report_files/`` (relative links, so the pair can be moved or
zipped together):

- a summary (scene counts, pass/fail, splits, the pass/fail rules used) and a
  dataset figure (dynamic range per scene, ghost vs saturated fractions);
- a thumbnail grid of the tone-mapped previews, failed scenes marked;
- a table with one row per scene (status, reasons, quality figures, split);
- per scene a figure: preview, response curves, histogram of log2 luminance
  (the dynamic range), saturation and ghost maps (mask bits 1 and 2), and
  example spectra at five pixels spread over the luminance range.

Figures are drawn with matplotlib's Agg backend.
"""

from __future__ import annotations

import contextlib
import html
import json
from pathlib import Path
from typing import Any

from mehs.dataset.manifest import read_manifest
from mehs.errors import InputError, MehsError

THUMB_MAX = 256


def write_dataset_report(dataset: str | Path, out_html: str | Path | None = None) -> Path:
    """Write the HTML report of ``dataset``; return the HTML path.

    Parameters
    ----------
    dataset
        A dataset folder written by ``mehs build`` (with ``manifest.json``).
    out_html
        Where to write the page (default ``DATASET/report.html``); images go to
        the folder ``<stem>_files`` beside it.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    from mehs.io.atomic import write_text_atomic
    from mehs.io.dirswap import (make_temp_folder, remove_path, remove_stale_temp_folders,
                                 replace_folder)

    dataset = Path(dataset)
    manifest = read_manifest(dataset)
    out_html = check_report_path(out_html) if out_html else dataset / "report.html"
    files_dir = out_html.parent / f"{out_html.stem}_files"
    # a killed run (SIGKILL, power loss) cannot clean up after itself: its unfinished
    # folder is no output and goes; another run's that is still drawing is left alone
    # (each run has its own, so two reports of one dataset at once both complete)
    remove_stale_temp_folders(files_dir, "unfinished report folder")
    tmp_dir = make_temp_folder(files_dir)
    try:
        page = _write_pictures_and_page(dataset, manifest, tmp_dir, files_dir.name)
        # the image folder first, then the page, so the page never points at missing
        # images; the previous images stay until the new ones are all in place
        replace_folder(tmp_dir, files_dir)
    except BaseException:
        # Ctrl-C, a full disk, a bug: no half folder left for a user to take for output;
        # a previous complete report is untouched
        with contextlib.suppress(MehsError):  # never hide the error that got us here
            remove_path(tmp_dir, "unfinished report folder")
        raise
    write_text_atomic(out_html, page)
    return out_html


def _write_pictures_and_page(dataset: Path, manifest: dict[str, Any], tmp_dir: Path,
                             rel: str) -> str:
    """Draw every picture into ``tmp_dir``; return the HTML page, linking them as ``rel/…``."""
    scenes = manifest["scenes"]
    split_of = {s: k for k, ids in manifest.get("splits", {}).items() for s in ids}

    cards, rows, details = [], [], []
    for s in scenes:
        sid = s["id"]
        files = s.get("files") or {}
        thumb = None
        if files.get("preview") and (dataset / files["preview"]).is_file():
            thumb = f"{sid}_thumb.png"
            _thumbnail(dataset / files["preview"], tmp_dir / thumb)
        fig = None
        if files.get("hs"):
            fig = f"{sid}_figure.png"
            try:
                _scene_figure(dataset, s, tmp_dir / fig, manifest.get("radiance_unit"))
            except (MehsError, OSError, ValueError) as exc:
                fig = None
                s = {**s, "reasons": s.get("reasons", []) + [f"report: {exc}"]}
        cards.append(_card(s, thumb and f"{rel}/{thumb}"))
        rows.append(_row(s, split_of.get(sid, "")))
        details.append(_detail(s, fig and f"{rel}/{fig}"))
    overview = "overview.png"
    _overview_figure(scenes, tmp_dir / overview)

    n_pass = sum(s["status"] == "pass" for s in scenes)
    return _PAGE.format(
        title=html.escape(f"ME HS dataset report: {dataset.resolve().name}"),
        n=len(scenes), n_pass=n_pass, n_fail=len(scenes) - n_pass,
        version=html.escape(str(manifest.get("software_version", ""))),
        splits=html.escape(", ".join(f"{k}: {len(v)}" for k, v in manifest.get("splits", {}).items())),
        rules=html.escape(json.dumps(manifest.get("quality_rules", {}), sort_keys=True)),
        ldr=html.escape(str(manifest.get("rgb", {}).get("ldr_exposure_rule", ""))),
        radiometry=_radiometry(manifest),
        overview=f"{rel}/{overview}",
        cards="\n".join(cards), rows="\n".join(rows), details="\n".join(details))


def check_report_path(out_html: str | Path) -> Path:
    """``out_html`` as a Path, or :class:`InputError` if it cannot be the report page.

    The name must end in ``.html``/``.htm``: a mistyped ``--out`` such as
    ``DATASET/manifest.json`` would otherwise be replaced by the HTML page,
    destroying the dataset it reports on.
    """
    out_html = Path(out_html)
    if out_html.is_dir():
        raise InputError("the report must be a .html file, not a folder", out_html)
    if out_html.suffix.lower() not in (".html", ".htm"):
        raise InputError("the report file name must end in .html (refusing to replace "
                         "another kind of file)", out_html)
    return out_html


def write_report(path: str | Path, out_html: str | Path | None = None) -> Path:
    """Report of a dataset folder, or of an SSR evaluation results folder.

    A folder with a dataset ``manifest.json`` gets the dataset report; a results
    folder written by ``mehs evaluate --out`` (see
    :func:`mehs.ssr.evaluate.is_evaluation_folder`) is handed to
    :func:`mehs.ssr.report.write_evaluation_report`.
    """
    from mehs.ssr.evaluate import is_evaluation_folder

    path = Path(path)
    if out_html is not None:
        out_html = check_report_path(out_html)
    if (path / "manifest.json").is_file():
        return write_dataset_report(path, out_html)
    if is_evaluation_folder(path):
        from mehs.ssr.report import write_evaluation_report

        return Path(write_evaluation_report(path, out_html))
    raise InputError("neither a dataset folder (no manifest.json) nor an evaluation "
                     "results folder (no evaluation.json)", path)


# ------------------------------------------------------------------ figures

def _thumbnail(src: Path, dst: Path) -> None:
    import cv2

    from mehs.preview import read_png, write_png

    img = read_png(src)
    h, w = img.shape[:2]
    f = THUMB_MAX / max(h, w)
    if f < 1:
        img = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))),
                         interpolation=cv2.INTER_AREA)
    write_png(dst, img)


def _scene_figure(dataset: Path, scene: dict[str, Any], out: Path,
                  unit: str | None = None) -> None:
    import matplotlib.pyplot as plt
    import numpy as np

    from mehs.io.envi import read_envi
    from mehs.io.exr import read_exr
    from mehs.preview import read_png
    from mehs.rgb import luminance

    files = scene["files"]
    cube = read_envi(dataset / files["hs"], memmap=True)
    rgb = read_exr(dataset / files["hdr_rgb"]).data[:, :, :3]
    mask = read_png(dataset / files["mask"]) if files.get("mask") else np.zeros(rgb.shape[:2], np.uint8)
    Y = luminance(rgb)

    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5), layout="constrained")
    ax = axes[0, 0]
    if files.get("preview"):
        ax.imshow(read_png(dataset / files["preview"]))
    ax.set_title(f"{scene['id']} ({scene['status']}): tone-mapped preview")
    ax.axis("off")

    ax = axes[0, 1]
    _plot_response(ax, dataset / files["response"] if files.get("response") else None)

    ax = axes[0, 2]
    q = scene.get("quality") or {}
    valid = (Y > 0) & (mask == 0)
    # the pixels the dynamic range counts (docs/science.md): ghosts (2) and no-signal
    # pixels (4) out, a lamp saturated in every exposure (1) in with its lower bound;
    # without it a 14-stop lamp scene showed a 9-stop histogram under "DR 14 stops"
    counted = (Y > 0) & ((mask & 6) == 0)
    if counted.any():
        ax.hist(np.log2(Y[counted]), bins=60, color="0.3")
    dr = q.get("dynamic_range_stops")
    ax.set_title("log2 luminance" + (f" — DR {dr:.1f} stops" if dr is not None else ""))
    ax.set_xlabel("log2 Y (relative)")
    ax.set_ylabel("pixels")

    for ax, bit, key, name, cmap in (
            (axes[1, 0], 1, "saturated_fraction", "saturated in every exposure", "Reds"),
            (axes[1, 1], 2, "ghost_fraction", "ghost (moved between exposures)", "Blues")):
        m = (mask & bit) > 0
        ax.imshow(m, cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
        # the manifest's figure, as the table shows it; unknown (an HS cube has no
        # bracket, ghosts not tested) is not 0 % (the empty mask bit said so)
        ax.set_title(f"{name}: {_fmt(q.get(key), True) if q.get(key) is not None else 'not measured'}")
        ax.axis("off")

    ax = axes[1, 2]
    ok = np.flatnonzero(valid.ravel())
    if ok.size:
        order = ok[np.argsort(Y.ravel()[ok], kind="stable")]
        picks = order[np.linspace(0, order.size - 1, 5).round().astype(int)]
        w = cube.samples
        specs = []
        for p in picks:
            r, c = divmod(int(p), w)
            specs.append((r, c, np.asarray(cube.data[r, c, :], dtype=np.float64)))
        neg = [-s[s < 0].min() for _, _, s in specs if (s < 0).any()]
        if neg:
            # a fused cube keeps its signed estimate: a dark pixel's spectrum is noise
            # around 0. On a log axis its negative samples were gaps and its small positive
            # ones dips over decades; a symmetric log axis, linear within the noise (the
            # largest negative magnitude shown), draws the noise as noise
            ax.set_yscale("symlog", linthresh=float(max(neg)))
            ax.axhline(0.0, color="0.6", lw=0.6)
        else:
            ax.set_yscale("log")
        for r, c, spec in specs:
            # zero samples cannot sit on a log axis: leave a gap (clamping them to 1e-12
            # stretched the axis over 14 decades and hid the spectra's shapes)
            ax.plot(cube.wavelengths, spec if neg else np.where(spec > 0, spec, np.nan),
                    label=f"(line {r}, sample {c})")
        ax.legend(fontsize=7)
    ax.set_title("example spectra (luminance 0–100 %)")
    ax.set_xlabel("wavelength (nm)")
    scale = q.get("radiance_scale")
    ax.set_ylabel(f"radiance [{unit or 'unit not recorded'}]"
                  + (f" × {scale:g}" if _number(scale) and scale != 1 else ""))
    _save(fig, out)


def _plot_response(ax, path: Path | None) -> None:
    import numpy as np

    ax.set_title("response curve g(Z) = ln(E·Δt)")
    g = None
    levels = None
    if path is not None and path.is_file():
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            g = _find_curve(data)
            levels = data.get("levels") if isinstance(data, dict) else None
        except (OSError, ValueError):
            g = None
    if g is None:
        ax.text(0.5, 0.5, "no response curve\n(HS cube input or linear)", ha="center",
                va="center", transform=ax.transAxes)
        return
    g = np.atleast_2d(np.asarray(g, dtype=np.float64))
    # (curves, levels); a per-band curve records its level count (more bands than
    # levels, an 8-bit camera's 300 bands, would fool the shape guess)
    if (g.shape[0] == levels and g.shape[1] != levels) or (levels is None
                                                           and g.shape[0] > g.shape[1]):
        g = g.T
    z = np.arange(g.shape[1])
    idx = np.unique(np.linspace(0, g.shape[0] - 1, min(6, g.shape[0])).round().astype(int))
    for i in idx:
        ax.plot(z, g[i], lw=1, label=f"curve {i}" if g.shape[0] > 1 else None)
    if g.shape[0] > 1:
        ax.legend(fontsize=7)
    ax.set_xlabel("Z (DN)")
    ax.set_ylabel("g")


def _find_curve(data: Any):
    """The largest numeric list-of-lists/list in a response JSON (``g``, ``curve``, …)."""
    if isinstance(data, dict):
        for key in ("g", "log_response", "curve", "curves", "response"):
            if key in data:
                found = _find_curve(data[key])
                if found is not None:
                    return found
        return None
    if isinstance(data, list) and data and all(isinstance(v, (int, float)) for v in data):
        return data if len(data) > 2 else None
    if isinstance(data, list) and data and all(isinstance(v, list) for v in data):
        return data
    return None


def _overview_figure(scenes: list[dict], out: Path) -> None:
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.6), layout="constrained")
    q = [(s["id"], s["status"], s.get("quality") or {}) for s in scenes]
    ids = [i for i, _, _ in q]
    colors = ["tab:green" if st == "pass" else "tab:red" for _, st, _ in q]
    # an unknown figure (None: an HS cube has no bracket, a scene that failed to build)
    # is drawn as missing, never as a 0-stop bar or a point at (0, 0) beside real zeros
    have = [i for i, (_, _, x) in enumerate(q) if _number(x.get("dynamic_range_stops"))]
    a.bar(have, [q[i][2]["dynamic_range_stops"] for i in have],
          color=[colors[i] for i in have])
    for i in sorted(set(range(len(ids))) - set(have)):
        a.text(i, 0, "n/a", ha="center", va="bottom", fontsize=7, rotation=90, color="0.4")
    a.set_xticks(range(len(ids)), ids, rotation=60, fontsize=7)
    a.set_ylim(bottom=0)  # stops are >= 0; "n/a" labels sit on the axis
    a.set_ylabel("dynamic range (stops)")
    a.set_title("dynamic range per scene (green pass, red fail)")
    both = [i for i, (_, _, x) in enumerate(q)
            if _number(x.get("saturated_fraction")) and _number(x.get("ghost_fraction"))]
    b.scatter([q[i][2]["saturated_fraction"] for i in both],
              [q[i][2]["ghost_fraction"] for i in both], c=[colors[i] for i in both])
    b.set_xlabel("saturated-in-all fraction")
    b.set_ylabel("ghost fraction")
    missing = len(q) - len(both)
    b.set_title("saturation vs ghosts" + (f" ({missing} not measured)" if missing else ""))
    b.set_xlim(left=0)  # fractions: autoscale's margin around all-zero data went negative
    b.set_ylim(bottom=0)
    _save(fig, out)


def _number(v: Any) -> bool:
    """A finite number (not None, NaN, a bool or text) that can be drawn."""
    import math

    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _save(fig, out: Path) -> None:
    import matplotlib.pyplot as plt

    from mehs.io.atomic import atomic_path

    with atomic_path(out) as tmp:
        # no timestamp/software text chunks: the same data gives the same bytes
        fig.savefig(tmp, format="png", dpi=80, metadata={"Software": None})
    plt.close(fig)


# ------------------------------------------------------------------ html

def _fmt(v: Any, pct: bool = False) -> str:
    if v is None:
        return "–"
    if isinstance(v, list):
        return " ".join(_fmt(x) for x in v)
    if pct and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)  # an int 0 from a hand-edited or older manifest is still a fraction
    if isinstance(v, float):
        return f"{v * 100:.2f} %" if pct else f"{v:.3g}"
    return html.escape(str(v))


def _fmt_ratios(ratios: Any) -> str:
    """``1 : 70.7 : 5000`` — three significant digits, never scientific notation."""
    import numpy as np

    if not isinstance(ratios, list) or not ratios:
        return "–"
    return " : ".join(np.format_float_positional(float(r), precision=3, unique=True,
                                                 fractional=False, trim="-")
                      for r in ratios if isinstance(r, (int, float)))


def _card(s: dict, thumb: str | None) -> str:
    sid = html.escape(s["id"])
    img = (f'<img src="{html.escape(thumb)}" alt="preview of {sid}">' if thumb
           else '<div class="noimg">no preview</div>')
    return (f'<a class="card {s["status"]}" href="#scene-{sid}">{img}'
            f'<span>{sid} — {s["status"]}</span></a>')


def _row(s: dict, split: str) -> str:
    q = s.get("quality") or {}
    return ("<tr class='{st}'><td><a href='#scene-{id}'>{id}</a></td><td>{st}</td><td>{split}</td>"
            "<td>{dr}</td><td>{sat}</td><td>{gh}</td><td>{inv}</td><td>{unres}</td><td>{ratios}</td>"
            "<td>{reasons}</td></tr>").format(
        id=html.escape(s["id"]), st=s["status"], split=html.escape(split),
        dr=_fmt(q.get("dynamic_range_stops")), sat=_fmt(q.get("saturated_fraction"), True),
        gh=_fmt(q.get("ghost_fraction"), True), inv=_fmt(q.get("invalid_fraction"), True),
        unres=_fmt(q.get("noise_floor_fraction"), True),
        ratios=_fmt_ratios(q.get("exposure_ratios")),
        reasons=html.escape("; ".join(s.get("reasons", []))))


def _detail(s: dict, fig: str | None) -> str:
    sid = html.escape(s["id"])
    body = (f'<img src="{html.escape(fig)}" alt="figures of {sid}">' if fig
            else "<p>No figures (scene not built).</p>")
    reasons = "".join(f"<li>{html.escape(r)}</li>" for r in s.get("reasons", []))
    reasons += "".join(f'<li class="warning">warning while building: {html.escape(w)}</li>'
                       for w in _build_warnings(s))
    inputs = html.escape(", ".join(s.get("provenance", {}).get("inputs", [])))
    return (f'<section id="scene-{sid}"><h3>{sid} — {s["status"]}</h3>'
            f'<ul>{reasons}</ul><p class="small">inputs: {inputs}</p>{body}</section>')


def _build_warnings(s: dict) -> list[str]:
    """The warnings recorded while the scene was built (``provenance.run.warnings``), as lines."""
    from mehs.dataset.scene_warnings import describe

    run = (s.get("provenance") or {}).get("run")
    found = run.get("warnings") if isinstance(run, dict) else None
    # a hand-edited or older manifest: anything but a list of objects is no record
    return [describe(w) for w in found if isinstance(w, dict)] if isinstance(found, list) else []


def _radiometry(manifest: dict) -> str:
    """The radiance unit line: red when the dataset is camera counts, not radiance."""
    unit = manifest.get("radiance_unit")
    cal = manifest.get("calibration") or {}
    if unit is None:
        return ('<p class="uncal" style="color:#c00;font-weight:bold">Radiance unit not recorded '
                '(built before radiometric calibration existed): treat as DN/ms, uncalibrated.</p>')
    if unit.startswith("DN"):
        return (f'<p class="uncal" style="color:#c00;font-weight:bold">Uncalibrated: the cubes are '
                f'{html.escape(unit)} (camera quantum efficiency included), not spectral radiance. '
                f'Calibrate with <code>mehs calibrate</code> and build with --calibration.</p>')
    u = cal.get("median_uncertainty")
    # an unrecorded uncertainty is unknown, not a perfect 0.00 %
    u = f"{float(u):.2%}" if _number(u) else "not recorded"
    return (f'<p class="cal">Radiance unit: <b>{html.escape(unit)}</b> (calibration '
            f'{html.escape(str(cal.get("method", "")))}, {html.escape(str(cal.get("path", "")))}, '
            f'median responsivity uncertainty {u}).</p>')


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 1.5em; color: #222; }}
.grid {{ display: flex; flex-wrap: wrap; gap: 10px; }}
.card {{ display: flex; flex-direction: column; width: 180px; text-decoration: none;
        color: inherit; border: 3px solid #4a4; padding: 3px; font-size: 0.85em; }}
.card.fail {{ border-color: #c33; }}
.card img {{ width: 100%; height: auto; image-rendering: pixelated; }}
.noimg {{ height: 120px; background: #eee; display: flex; align-items: center;
          justify-content: center; }}
table {{ border-collapse: collapse; font-size: 0.85em; }}
td, th {{ border: 1px solid #ccc; padding: 2px 6px; text-align: right; }}
td:first-child, td:last-child, th:last-child {{ text-align: left; }}
tr.fail {{ background: #fdd; }}
section img {{ max-width: 100%; }}
.small {{ font-size: 0.8em; color: #555; }}
</style></head><body>
<h1>{title}</h1>
<p>{n} scenes: {n_pass} pass, {n_fail} fail. Splits (passing scenes only): {splits}.
mehs {version}.</p>
{radiometry}
<p class="small">Pass/fail rules: {rules}<br>LDR exposure rule: {ldr}</p>
<img src="{overview}" alt="dataset overview">
<h2>Previews</h2>
<div class="grid">
{cards}
</div>
<h2>Scenes</h2>
<table><thead><tr><th>scene</th><th>status</th><th>split</th><th>DR (stops)</th>
<th>saturated</th><th>ghost</th><th>invalid</th>
<th title="ground truth not resolved above its noise (mask bit 8): not scored">unresolved</th>
<th>exposure ratios</th><th>reasons</th></tr></thead>
<tbody>
{rows}
</tbody></table>
<h2>Per-scene figures</h2>
{details}
</body></html>
"""
