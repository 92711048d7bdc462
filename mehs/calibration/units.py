"""The spectral-radiance unit of a calibrated source's certificate, and its factor to SI.

Certificates print radiance in many units: W·sr⁻¹·m⁻²·nm⁻¹ (SI per nm), W/(cm²·sr·nm)
(10⁴× the SI value), µW/(cm²·sr·nm), W/(m²·sr·µm) (10⁻³×), W·cm⁻³·sr⁻¹ (the wavelength's
length folded into the area: per cm, 10⁻³×) — a factor 10⁻⁹…10⁴ that a bare table of numbers
does not show. mehs reads the unit from the certificate's header
(or ``--source-unit``), converts to :data:`SI_RADIANCE`, and records what it did; a
table without a unit is taken as SI and says so; a header whose unit mehs cannot convert
(per Hz, a printed multiplier "×10⁻⁶") is refused, not taken as SI. A spectral *irradiance* (no sr⁻¹: a
standard lamp's certificate) is refused: it is not the radiance of anything until a
diffuse panel at a stated distance turns it into ``ρ·E/π``.

References
----------
- BIPM (2019). The International System of Units (SI), 9th ed. (prefixes, units).
- Yoon, H. W. and Gibson, C. E. (2011). Spectral irradiance calibrations. NIST SP 250-89.
"""

from __future__ import annotations

import re
from typing import Any

from mehs.errors import InputError

SI_RADIANCE = "W sr-1 m-2 nm-1"

_POWER = {"kw": 1e3, "w": 1.0, "mw": 1e-3, "uw": 1e-6, "nw": 1e-9}
_AREA = {"m": 1.0, "cm": 1e4, "mm": 1e6}                 # per cm² = 10⁴ per m²
_PER_WAVELENGTH = {"nm": 1.0, "um": 1e-3, "micron": 1e-3, "microns": 1e-3}
#: per volume (W·m⁻³·sr⁻¹): per area × per length of wavelength, 1 m = 10⁹ nm, 1 cm = 10⁷ nm
_VOLUME = {"m": 1.0 * 1e-9, "cm": 1e4 * 1e-7, "mm": 1e6 * 1e-6}
#: a power unit as a word of its own: "kW", "W", "mW", "µW", "uW", "nW"
_POWER_RE = re.compile(r"(?<![A-Za-z])([knuµμm]?W)(?![A-Za-z])")
#: a scale printed beside a unit ("x 1e-6", "×10⁻⁶", "10^-6 W…"): values are not in the unit
_MULTIPLIER_RE = re.compile(r"(?<![A-Za-z])[x×*]\s*10\s*(?:\^|\*\*)?\s*[-−⁻+]?\s*[\d⁰¹²³⁴⁵⁶⁷⁸⁹]"
                            r"|10\s*(?:\^|\*\*)\s*[-−+]?\s*\d|10[⁻⁺]?[⁰¹²³⁴⁵⁶⁷⁸⁹]"
                            r"|(?<![\w.])\d+(?:\.\d*)?[eE][-+−]?\d+")
#: a radiance-looking expression (per sr) that no conversion was found for
_RADIOMETRIC_RE = re.compile(r"\bsr\b")


def _normalise(text: str) -> str:
    t = text.replace("µ", "u").replace("μ", "u").replace("−", "-").replace("⁻", "-")
    t = t.replace("²", "2").replace("³", "3").replace("¹", "1").replace("^", "")
    return t.lower()


def parse_radiance_unit(text: str) -> dict[str, Any] | None:
    """The unit of one unit expression (``"W/(cm2 sr nm)"``, ``"uW cm-2 sr-1 nm-1"``).

    Returns ``{"unit", "factor", "radiance"}`` (``factor``: multiply values by it to get
    :data:`SI_RADIANCE`; ``radiance``: False for an irradiance, no sr), or None when
    ``text`` is not a spectral quantity (no area or no per-wavelength term: "1000 W lamp").
    """
    m = _POWER_RE.search(text)
    if m is None:
        return None
    frag = _normalise(text[m.start():])
    power = area = per_wl = volume = None
    sr = False
    for word, exp in re.findall(r"([a-z]+)\s*(-?\d*)", frag):
        if power is None and word in _POWER:
            power = _POWER[word]
        elif word in _AREA and exp.lstrip("-") == "2" and area is None:
            area = _AREA[word]
        elif word in _VOLUME and exp.lstrip("-") == "3" and volume is None:
            volume = _VOLUME[word]
        elif word == "sr":
            sr = True
        elif word in _PER_WAVELENGTH and exp.lstrip("-") in ("", "1") and per_wl is None:
            per_wl = _PER_WAVELENGTH[word]
    if power is not None and volume is not None and area is None and per_wl is None:
        return {"unit": text[m.start():].strip(), "factor": power * volume, "radiance": sr}
    if power is None or area is None or per_wl is None:
        return None
    return {"unit": text[m.start():].strip(), "factor": power * area * per_wl, "radiance": sr}


def header_units(header: str) -> list[dict[str, Any]]:
    """Every unit expression found in a certificate's header lines (comments, column names).

    An expression that looks like a radiance (a power per sr) but has no
    conversion, or a unit with a scale printed beside it, comes back as
    ``{"unit", "factor": None, "radiance": None}``: :func:`source_unit` refuses it.
    """
    found = []
    for line in header.splitlines():
        # a unit ends at a column or clause separator: "…nm-1; third column: …"
        for part in re.split(r"[,;\t]", line):
            for m in _POWER_RE.finditer(part):
                u = parse_radiance_unit(part[m.start():])
                if u is not None:
                    if _MULTIPLIER_RE.search(part):
                        # "(W/(cm2 sr nm)) x 1e-6": the values are not in the unit named
                        found.append({"unit": part.strip(), "factor": None, "radiance": None})
                    else:
                        found.append(u)
                    break
                if _RADIOMETRIC_RE.search(_normalise(part[m.start():])):
                    # W m-2 sr-1 Hz-1, W/(sr ft2 nm), …: taken as SI it would be silently wrong
                    found.append({"unit": part[m.start():].strip(), "factor": None,
                                  "radiance": None})
                    break
    return found


def source_unit(header: str, declared: str | None, source: Any = None) -> dict[str, Any]:
    """The certificate's unit: ``declared`` (``--source-unit``), else its header's, else SI assumed.

    Returns ``{"unit", "factor", "from"}`` with ``from`` one of ``"option"``,
    ``"header"``, ``"assumed"``. Raises :class:`InputError` for an irradiance, an
    unreadable declared unit, or a header naming two different units.
    """
    if declared is not None:
        u = parse_radiance_unit(declared if _POWER_RE.search(declared) else "W " + declared)
        if u is None:
            raise InputError(f"--source-unit {declared!r} is not a spectral radiance unit "
                             f"(e.g. '{SI_RADIANCE}', 'uW cm-2 sr-1 nm-1', 'W/(m2 sr um)')")
        how = "option"
    else:
        found = header_units(header)
        if not found:
            return {"unit": SI_RADIANCE, "factor": 1.0, "from": "assumed"}
        bad = [f for f in found if f["factor"] is None]
        if bad:
            raise InputError(f"the certificate's header names a unit mehs cannot convert "
                             f"({bad[0]['unit']!r}: per Hz, a scale printed beside it, …); give "
                             f"the values' unit with --source-unit (e.g. '{SI_RADIANCE}', "
                             "or 'uW m-2 sr-1 nm-1' for values in 1e-6 W m-2 sr-1 nm-1)", source)
        if len({f["factor"] for f in found}) > 1 or len({f["radiance"] for f in found}) > 1:
            raise InputError("the certificate's header names more than one unit ("
                             + "; ".join(repr(f["unit"]) for f in found)
                             + "); give the values' unit with --source-unit", source)
        u, how = found[0], "header"
    if not u["radiance"]:
        raise InputError(f"the certificate is a spectral irradiance ({u['unit']!r}, no sr-1): a "
                         "standard lamp's irradiance E becomes a radiance only on a diffuse "
                         "panel, L = rho*E/pi at the certificate's distance; give the panel's "
                         f"radiance in {SI_RADIANCE}", source)
    return {"unit": u["unit"], "factor": float(u["factor"]), "from": how}
