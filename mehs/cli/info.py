"""`mehs info PATH` — summarise an ENVI cube, a Specim IQ folder or an OpenEXR image.

Reads headers and at most ``--lines`` evenly spaced lines of the data (memory
mapped), so a 512×512×204 cube answers in a few milliseconds; statistics from
a subset are labelled ``sampled``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: 12-bit sensors (Specim IQ) saturate at this DN.
SATURATION_12BIT = 4095


def configure(parser) -> None:
    parser.add_argument("path", metavar="PATH", nargs="?", default=None,
                        help="ENVI .hdr (or its data file), Specim IQ capture folder, or .exr; "
                             "without PATH: the versions of mehs, Python and its libraries, "
                             "and which extras are installed (for a bug report)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--lines", type=int, default=64, metavar="N",
                        help="sample at most N evenly spaced lines for the value "
                             "statistics (default 64; 0 = all lines)")
    parser.add_argument("--allow-missing-dark", action="store_true",
                        help="describe a Specim IQ folder that has no dark reference "
                             "(by default that is an error, as for every other command)")
    parser.add_argument("--saturation", type=float, default=None, metavar="DN",
                        help="saturation level for integer data (default: 4095 when the "
                             "sampled values fit 12 bits, else the type's maximum)")


def run(args) -> int:
    import warnings

    if args.path is None:
        from mehs.cli import versions_text

        print(versions_text())
        return 0

    from mehs.io.plausibility import ByteOrderWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ByteOrderWarning)  # shown as a line of the summary
        info = describe(args.path, max_lines=args.lines, saturation=args.saturation,
                        require_dark=not args.allow_missing_dark)
    if args.json:
        print(json.dumps(info, indent=2, default=_json_default))
    else:
        print(format_text(info))
    return 0


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


# ------------------------------------------------------------------ describing


def describe(path: str | Path, *, max_lines: int = 64, saturation: float | None = None,
             require_dark: bool = True) -> dict[str, Any]:
    """Summary dict of an ENVI file, a Specim IQ folder or an EXR (see module doc).

    ``require_dark`` is passed to :func:`mehs.io.specim.read_specim_folder`.

    Raises
    ------
    InputError, FormatError
        Missing path or a file that does not follow its format.
    """
    import math

    from mehs.errors import InputError
    from mehs.io.specim import is_specim_folder

    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        # a level <= 0 would report every pixel as saturated
        raise InputError(f"--saturation must be a positive DN level, got {saturation}")
    p = Path(path)
    if not p.exists():
        raise InputError("file or folder does not exist", p)
    if max_lines < 0:
        raise InputError(f"--lines must be ≥ 0, got {max_lines}")
    if p.is_dir():
        if is_specim_folder(p):
            return _describe_specim(p, max_lines, saturation, require_dark)
        # a published IQ result without capture/ (REFLECTANCE_<id>.hdr/.dat + <id>.png)
        results = sorted({*p.glob("REFLECTANCE_*.hdr"), *p.glob("results/REFLECTANCE_*.hdr")})
        if len(results) == 1:
            return _describe_envi(results[0], max_lines, saturation)
        raise InputError("folder is not a Specim IQ capture (no manifest.xml or "
                         "capture/<id>.hdr)", p)
    if p.suffix.lower() == ".exr":
        return _describe_exr(p)
    return _describe_envi(p, max_lines, saturation)


def _sample_lines(n_lines: int, max_lines: int):
    import numpy as np

    if max_lines == 0 or n_lines <= max_lines:
        return np.arange(n_lines), False
    return np.unique(np.linspace(0, n_lines - 1, max_lines).round().astype(np.intp)), True


def _value_stats(sample, *, integer: bool, saturation: float | None) -> dict[str, Any]:
    import numpy as np

    out: dict[str, Any] = {}
    if sample.size == 0:
        return out
    finite = np.isfinite(sample) if not integer else None
    if finite is not None and not finite.all():
        out["non_finite_values"] = int(sample.size - finite.sum())
        vals = sample[finite]
    else:
        vals = sample
    if vals.size:
        out["min"] = vals.min().item()
        out["max"] = vals.max().item()
        out["mean"] = float(vals.mean(dtype=np.float64))
    if integer or saturation is not None:
        level = saturation
        if level is None:
            if out.get("max", 0) <= SATURATION_12BIT:
                level, note = SATURATION_12BIT, "12-bit"
            else:
                level, note = np.iinfo(sample.dtype).max, f"{sample.dtype.itemsize * 8}-bit"
        else:
            note = "given"
        sat = sample >= level
        out["saturation_level"] = float(level)
        out["saturation_level_basis"] = note
        out["saturated_fraction"] = float(sat.mean())
        out["saturated_pixel_fraction"] = float(sat.any(axis=-1).mean())
    return out


def _describe_envi(path: Path, max_lines: int, saturation: float | None) -> dict[str, Any]:
    import numpy as np

    from mehs.io import envi

    hdr = envi.read_envi_header(path)
    kw = envi._cube_fields(hdr)
    wl = kw["wavelengths"]
    info: dict[str, Any] = {
        "format": "ENVI", "path": str(path), "header": str(hdr.header_path),
        "data_file": str(hdr.data_path),
        "shape": [hdr.lines, hdr.samples, hdr.bands], "shape_axes": "lines, samples, bands",
        "dtype": hdr.dtype.newbyteorder("=").name, "interleave": hdr.interleave,
        "byte_order": f"{hdr.byte_order} ({'little' if hdr.byte_order == 0 else 'big'}-endian)",
        "header_offset": hdr.header_offset, "file_bytes": hdr.data_path.stat().st_size,
        "wavelengths": {"count": int(wl.size), "min_nm": float(wl.min()),
                        "max_nm": float(wl.max()), "sorted": bool(np.all(np.diff(wl) > 0)),
                        "in_400_700": int(((wl >= 400) & (wl <= 700)).sum())},
        "fwhm": None if kw.get("fwhm") is None else
        {"min_nm": float(kw["fwhm"].min()), "max_nm": float(kw["fwhm"].max())},
        "integration_time_ms": kw.get("integration_time_ms"),
        "acquisition_date": kw.get("acquisition_date"),
        "binning": list(kw["binning"]) if kw.get("binning") else None,
        "units": str(hdr.fields["data units"]).strip() if "data units" in hdr.fields else None,
    }
    u = info["units"] or ""
    info["radiometric"] = ("calibrated" if u in ("W sr-1 m-2 nm-1", "relative radiance")
                           else "uncalibrated" if u.startswith("DN/ms") else None)
    db = kw.get("default_bands")
    info["default_bands"] = None if db is None else [
        {"band": b + 1, "nm": float(wl[b])} for b in db]
    from mehs.io.envi_keys import reflectance_scale

    sf = reflectance_scale(hdr.fields, hdr.header_path)   # "abc" or 0: named, as read_envi does
    if sf is not None:
        info["reflectance_scale_factor"] = sf
    from mehs.io.plausibility import byte_order_message, byte_order_suspicion

    why = byte_order_suspicion(hdr.open_memmap())
    info["byte_order_warning"] = None if why is None else byte_order_message(why, hdr.byte_order)
    idx, sampled = _sample_lines(hdr.lines, max_lines)
    sample = np.asarray(hdr.open_memmap()[idx])
    if sf is not None and sf != 1.0:
        sample = sample.astype(np.float32) / np.float32(sf)
    integer = sample.dtype.kind in "iu"
    stats = _value_stats(sample, integer=integer, saturation=saturation)
    stats["sampled"] = bool(sampled)
    stats["lines_read"] = int(idx.size)
    info["values"] = stats
    return info


def _describe_specim(path: Path, max_lines: int, saturation: float | None,
                     require_dark: bool) -> dict[str, Any]:
    import numpy as np

    from mehs.io.specim import read_specim_folder

    cap = read_specim_folder(path, require_dark=require_dark)
    info: dict[str, Any] = {"format": "Specim IQ capture folder", "path": str(path),
                            "capture_id": cap.capture_id,
                            "manifest": (path / "manifest.xml").is_file()}
    refs = {}
    for kind in ("darkref", "whiteref", "whitedarkref", "reflectance"):
        c = getattr(cap, kind)
        if c is None:
            refs[kind] = None
            continue
        entry: dict[str, Any] = {"file": str(c.source), "shape": list(c.shape),
                                 "dtype": c.data.dtype.name}
        if kind != "reflectance":  # references are usually one line; sample if not
            idx, sampled = _sample_lines(c.lines, max_lines)
            d = np.asarray(c.data[idx])
            entry.update(min=d.min().item(), max=d.max().item(),
                         mean=float(d.mean(dtype=np.float64)), sampled=sampled)
        refs[kind] = entry
    info["references"] = refs
    info["missing"] = [k for k in ("darkref", "whiteref") if refs[k] is None]
    info["preview"] = None if cap.preview is None else list(cap.preview.shape)
    info["metadata_keys"] = len(cap.metadata)
    info["raw"] = _describe_envi(Path(cap.raw.source), max_lines, saturation)
    return info


def _describe_exr(path: Path) -> dict[str, Any]:
    import numpy as np

    from mehs.io.exr import read_exr, spectral_channels

    img = read_exr(path, check_finite=True)
    d = img.data
    info: dict[str, Any] = {
        "format": "OpenEXR", "path": str(path), "shape": list(d.shape),
        "shape_axes": "height, width, channels", "channels": len(img.channels),
        "channel_names": img.channels if len(img.channels) <= 8
        else img.channels[:4] + ["…"] + img.channels[-2:],
        "compression": str(img.header.get("compression", "")) or None,
        "values": {"min": float(d.min()), "max": float(d.max()),
                   "mean": float(d.mean(dtype=np.float64)), "sampled": False},
    }
    idx, wl = spectral_channels(img.channels)
    if idx:
        info["wavelengths"] = {"count": len(idx), "min_nm": float(wl.min()),
                               "max_nm": float(wl.max())}
    return info


# ------------------------------------------------------------------ text output


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def format_text(info: dict[str, Any], indent: str = "") -> str:
    """Human-readable lines for a :func:`describe` summary."""
    lines = []
    if info["format"] == "Specim IQ capture folder":
        lines.append(f"{indent}{info['path']}: Specim IQ capture '{info['capture_id']}'"
                     f"{'' if info['manifest'] else ' (no manifest.xml)'}")
        for kind, r in info["references"].items():
            if r is None:
                lines.append(f"{indent}  {kind:<13} missing")
            else:
                rng = f", values {_fmt(r['min'])}..{_fmt(r['max'])} (mean {_fmt(r['mean'])})" \
                    if "min" in r else ""
                lines.append(f"{indent}  {kind:<13} {' × '.join(map(str, r['shape']))} "
                             f"{r['dtype']}{rng}")
        lines.append(f"{indent}  preview       "
                     f"{'missing' if info['preview'] is None else '×'.join(map(str, info['preview']))}")
        lines.append(f"{indent}  metadata      {info['metadata_keys']} keys")
        lines.append(f"{indent}  raw cube:")
        lines.append(format_text(info["raw"], indent + "    "))
        return "\n".join(lines)
    v = info.get("values", {})
    if info["format"] == "OpenEXR":
        lines += [f"{indent}{info['path']}: OpenEXR",
                  f"{indent}  shape         {' × '.join(map(str, info['shape']))} "
                  f"({info['shape_axes']})",
                  f"{indent}  channels      {', '.join(info['channel_names'])}"]
        if "wavelengths" in info:
            w = info["wavelengths"]
            lines.append(f"{indent}  wavelengths   {w['count']} bands, "
                         f"{_fmt(w['min_nm'])}–{_fmt(w['max_nm'])} nm")
        lines.append(f"{indent}  values        {_fmt(v['min'])} .. {_fmt(v['max'])} "
                     f"(mean {_fmt(v['mean'])})")
        return "\n".join(lines)
    w = info["wavelengths"]
    lines += [
        f"{indent}{info['header']}: ENVI",
        f"{indent}  data file     {info['data_file']} ({info['file_bytes']} bytes, "
        f"header offset {info['header_offset']})",
        f"{indent}  shape         {' × '.join(map(str, info['shape']))} ({info['shape_axes']})",
        f"{indent}  dtype         {info['dtype']}, interleave {info['interleave']}, "
        f"byte order {info['byte_order']}",
        *([f"{indent}  WARNING       {info['byte_order_warning']}"]
          if info.get("byte_order_warning") else []),
        f"{indent}  wavelengths   {w['count']} bands, {_fmt(w['min_nm'])}–{_fmt(w['max_nm'])} nm"
        f"{'' if w['sorted'] else ' (NOT sorted in the file)'}, {w['in_400_700']} in 400–700 nm",
    ]
    if info["fwhm"]:
        lines.append(f"{indent}  fwhm          {_fmt(info['fwhm']['min_nm'])}–"
                     f"{_fmt(info['fwhm']['max_nm'])} nm")
    lines.append(f"{indent}  integration   "
                 f"{'unknown' if info['integration_time_ms'] is None else _fmt(info['integration_time_ms']) + ' ms'}")
    lines.append(f"{indent}  date          {info['acquisition_date'] or 'unknown'}")
    if info["default_bands"]:
        lines.append(f"{indent}  default bands " + ", ".join(
            f"{d['band']} ({d['nm']:.1f} nm)" for d in info["default_bands"]))
    if info["binning"]:
        lines.append(f"{indent}  binning       {info['binning']}")
    if info.get("units"):
        note = {"uncalibrated": " — UNCALIBRATED: camera counts per ms (quantum efficiency "
                                "included), not radiance; see mehs calibrate",
                "calibrated": " (radiometrically calibrated)"}.get(info.get("radiometric"), "")
        lines.append(f"{indent}  units         {info['units']}{note}")
    if "reflectance_scale_factor" in info:
        lines.append(f"{indent}  scale factor  {_fmt(info['reflectance_scale_factor'])} "
                     "(values below divided by it)")
    label = (f"sampled {v['lines_read']} of {info['shape'][0]} lines" if v.get("sampled")
             else "all lines")
    if "min" in v:
        lines.append(f"{indent}  values        {_fmt(v['min'])} .. {_fmt(v['max'])} "
                     f"(mean {_fmt(v['mean'])}; {label})")
    if "non_finite_values" in v:
        lines.append(f"{indent}  non-finite    {v['non_finite_values']} values (NaN/Inf)")
    if "saturated_fraction" in v:
        lines.append(f"{indent}  saturation    {100 * v['saturated_fraction']:.4g} % of values, "
                     f"{100 * v['saturated_pixel_fraction']:.4g} % of pixels ≥ "
                     f"{_fmt(v['saturation_level'])} ({v['saturation_level_basis']}; {label})")
    return "\n".join(lines)
