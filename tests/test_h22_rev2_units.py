"""Certificate units mehs did not read were silently taken as SI (review r2).

Independent truth: SI definitions only (1 cm = 10⁷ nm, 1 m = 10⁹ nm, 1 cm² = 10⁻⁴ m²):
a spectral radiance per unit *volume* (W·cm⁻³·sr⁻¹, W·m⁻³·sr⁻¹: the per-wavelength length
folded into the area, as NIST strip-lamp tables and Planck's law in SI print it) is
W·m⁻²·sr⁻¹ per cm / per m of wavelength: ×10⁴/10⁷ = 10⁻³ and ×1/10⁹ = 10⁻⁹ of
W·sr⁻¹·m⁻²·nm⁻¹. A header unit mehs cannot convert (per Hz, a printed multiplier) must be
refused by name, not taken as W·sr⁻¹·m⁻²·nm⁻¹ ("assumed", a 10³–10⁹ error).
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.calibration.spectra import load_spectrum
from mehs.calibration.units import parse_radiance_unit, source_unit
from mehs.errors import InputError


@pytest.mark.parametrize("text,factor", [
    ("W cm-3 sr-1", 1e4 / 1e7),
    ("W m-3 sr-1", 1.0 / 1e9),
    ("W/(m^3 sr)", 1.0 / 1e9),
    ("W·cm⁻³·sr⁻¹", 1e-3),
    ("kW/(m2 sr um)", 1e3 / 1e3),
])
def test_volume_and_kilowatt_radiance_units_convert(text, factor):
    u = parse_radiance_unit(text)
    assert u is not None and u["radiance"]
    assert u["factor"] == pytest.approx(factor, rel=1e-12)
    got = source_unit(f"wavelength (nm), spectral radiance ({text})", None)
    assert got["from"] == "header" and got["factor"] == pytest.approx(factor, rel=1e-12)


@pytest.mark.parametrize("header", [
    "wavelength (nm), radiance (W m-2 sr-1 Hz-1)",          # per frequency: not per nm
    "wavelength (nm), radiance (W/(cm2 sr nm)) x 1e-6",      # a printed multiplier
    "wavelength (nm), radiance [10^-6 W/(cm2 sr nm)]",
    "wavelength (nm), radiance (×10⁻³ W m-2 sr-1 nm-1)",
])
def test_unreadable_header_unit_is_refused_not_assumed_si(header):
    with pytest.raises(InputError, match="--source-unit"):
        source_unit(header, None)
    # the option still decides
    assert source_unit(header, "uW cm-2 sr-1 nm-1")["factor"] == pytest.approx(1e-2)


def test_ordinary_headers_still_read(tmp_path):
    p = tmp_path / "cert.csv"
    rows = "\n".join(f"{w},{v:.6e}" for w, v in zip(range(400, 701, 10), np.linspace(1, 2, 31)))
    p.write_text("# Labsphere 1000 W QTH lamp at 50 cm, certificate 12-345, 2021\n"
                 "# range 400-700 nm, 3000 K\n"
                 f"nm,W sr-1 m-2 nm-1\n{rows}\n", encoding="utf-8")
    s = load_spectrum(p)
    assert source_unit(s.header, None) == {"unit": "W sr-1 m-2 nm-1", "factor": 1.0,
                                           "from": "header"}
    p.write_text(f"# Labsphere 1000 W QTH lamp at 50 cm\n{rows}\n", encoding="utf-8")
    assert source_unit(load_spectrum(p).header, None)["from"] == "assumed"


@pytest.mark.parametrize("first", ["1000 W QTH lamp, certificate 12-345",
                                   "2021-03-04 calibration at 3000 K"])
def test_header_line_starting_with_a_digit_keeps_the_unit_lines_after_it(tmp_path, first):
    # the table reader skips such a line as a header; the unit reader stopped there and
    # took the W/(cm2 sr nm) values as SI: 10^4 too small a radiance
    p = tmp_path / "cert.csv"
    rows = "\n".join(f"{w},{v:.6e}" for w, v in zip(range(400, 701, 10), np.linspace(1, 2, 31)))
    p.write_text(f"{first}\nwavelength (nm), radiance (W/(cm2 sr nm))\n{rows}\n", encoding="utf-8")
    s = load_spectrum(p)
    assert s.values.size == 31
    got = source_unit(s.header, None)
    assert got["from"] == "header" and got["factor"] == pytest.approx(1e4)
