"""Fichet 2021 spectral EXR channels named by frequency or with any SI prefix, and bi-spectral
re-radiation channels: files written with the OpenEXR bindings in the layout's exact names,
wavelengths checked against λ = c/ν (c exact by the SI) and colour-science's own parser."""

import numpy as np
import pytest

from mehs.errors import FormatError
from mehs.io.exr import parse_spectral_channel
from mehs.io.exr_spectral import read_exr_spectral

C = 299792458.0


def _write(path, channels: dict[str, np.ndarray]):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v, dtype=np.float32)
                               for k, v in channels.items()}) as f:
        f.write(str(path))


def _thz(nm: float) -> str:
    return f"{C / (nm * 1e-9) / 1e12:.6f}".replace(".", ",") + "THz"


def test_frequency_named_channels_read_as_their_wavelengths(tmp_path):
    nms = [400.0, 550.0, 700.0]
    rng = np.random.default_rng(0)
    planes = {f"S0.{_thz(nm)}": rng.uniform(0, 1, (3, 4)) for nm in nms}
    _write(tmp_path / "f.exr", planes)
    cube = read_exr_spectral(tmp_path / "f.exr")
    np.testing.assert_allclose(cube.wavelengths, nms, rtol=1e-8)
    # band order follows the wavelength, which runs against the frequency
    np.testing.assert_array_equal(np.asarray(cube.data)[:, :, 0], planes[f"S0.{_thz(400)}"].astype(np.float32))


@pytest.mark.parametrize("name, nm", [("S0.400nm", 400.0), ("S0.0,4um", 400.0),
                                      ("S0.0,0004mm", 400.0), ("T.4e-7m", 400.0),
                                      ("S0.4000Ang", None), ("S0.0,749481PHz", 400.0),
                                      ("S0.749481,145GHz", 400.0), ("S0.0Hz", None),
                                      ("S0.40dam", 4e11)])
def test_quantities_with_si_prefixes(name, nm):
    got = parse_spectral_channel(name)
    if nm is None:
        assert got is None
    else:
        assert got[0] == name.split(".")[0] and got[1] == pytest.approx(nm, rel=1e-6)


def test_the_parser_agrees_with_colour_science():
    """colour.io's Fichet 2021 regex and unit conversion, on the same names."""
    import re

    from colour.io.fichet2021 import PATTERN_FICHET2021, match_groups_to_nm

    pat = re.compile(rf"^(S[0-3])\.*{PATTERN_FICHET2021}$")
    for name in ["S0.400nm", "S0.549,5nm", "S0.0,55um", "S0.545,06THz", "S0.0,6PHz",
                 "S0.700000pm"]:
        m = pat.match(name)
        ref = match_groups_to_nm(m.group(2), m.group(4) or "", m.group(5))
        assert parse_spectral_channel(name)[1] == pytest.approx(ref, rel=1e-12), name


def test_bispectral_channels_are_named_not_taken_for_bands(tmp_path):
    z = np.zeros((2, 2))
    _write(tmp_path / "b.exr", {"T.400nm": z + 0.5, "T.500nm": z + 0.4,
                                "T.400nm.500nm": z + 0.1})
    with pytest.warns(UserWarning, match="re-radiation"):
        cube = read_exr_spectral(tmp_path / "b.exr")
    np.testing.assert_allclose(cube.wavelengths, [400, 500])
    _write(tmp_path / "only.exr", {"T.400nm.500nm": z})
    with pytest.raises(FormatError, match="re-radiation") as err:
        read_exr_spectral(tmp_path / "only.exr")
    assert "only.exr" in str(err.value)
