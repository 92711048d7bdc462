import colour
import numpy as np

from mehs.rgb import WAVELENGTHS_31, spectra_to_XYZ, spectra_to_linear_sRGB


def test_flat_spectrum_has_unit_Y():
    xyz = spectra_to_XYZ(np.ones(31), WAVELENGTHS_31)
    assert abs(xyz[1] - 1) < 1e-12


def test_d65_is_white():
    d65 = colour.SDS_ILLUMINANTS["D65"]
    s = np.interp(WAVELENGTHS_31, d65.wavelengths, d65.values)
    rgb = spectra_to_linear_sRGB(s, WAVELENGTHS_31)
    y = spectra_to_XYZ(s, WAVELENGTHS_31)[1]
    np.testing.assert_allclose(rgb / y, 1, atol=0.01)
