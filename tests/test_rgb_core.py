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


def _specim_iq_centres_400_700():
    """A Specim IQ's band centres (204 over 397.3–1003.6 nm, about 2.96 nm apart, a
    quadratic dispersion), those inside 400–700 nm: unevenly spaced."""
    i = np.arange(204, dtype=np.float64)
    wl = 397.32 + 2.8824 * i + 3.94e-4 * i * i
    return wl[(wl >= 400) & (wl <= 700)]


def test_uneven_bands_integrate_with_their_widths_as_colour_science_does():
    """XYZ of unevenly spaced bands equals colour-science's ``sd_to_XYZ`` (Integration)
    of the same samples at 1 nm; without the band widths the denser end of the
    spectrum counted for more (D65 white ΔE00 ≈ 0.9 on Specim IQ centres)."""
    wl = _specim_iq_centres_400_700()
    steps = np.diff(wl)
    assert steps.max() - steps.min() > 0.05                 # genuinely uneven
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    shape = colour.SpectralShape(int(np.ceil(wl[0])), int(np.floor(wl[-1])), 1)
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    for name in ("D65", "A", "FL2"):
        ill = colour.SDS_ILLUMINANTS[name]
        s = np.interp(wl, ill.wavelengths, ill.values)
        sd = colour.SpectralDistribution(s, wl, interpolator=colour.LinearInterpolator)
        ref = colour.sd_to_XYZ(sd.copy().align(shape), cmfs.copy().trim(shape),
                               method="Integration") / 100
        got = spectra_to_XYZ(s, wl)
        lab = [colour.XYZ_to_Lab(x / ref[1], d65) for x in (got, ref)]
        assert colour.delta_E(*lab, method="CIE 2000") < 0.15, name
    # a flat spectrum still has Y = 1, in any band order
    perm = np.random.default_rng(0).permutation(wl.size)
    assert np.isclose(spectra_to_XYZ(np.ones(wl.size), wl[perm])[1], 1.0, rtol=1e-12)
    s = np.interp(wl, colour.SDS_ILLUMINANTS["A"].wavelengths, colour.SDS_ILLUMINANTS["A"].values)
    np.testing.assert_allclose(spectra_to_XYZ(s[perm], wl[perm]), spectra_to_XYZ(s, wl),
                               rtol=1e-12)


def test_evenly_spaced_bands_keep_the_papers_plain_sum():
    """For even spacing the widths cancel: ``M = [x̄ ȳ z̄] / Σȳ`` to the bit."""
    from mehs.rgb import _cmfs_at, cmfs_matrix

    for wl in (WAVELENGTHS_31, np.arange(402.5, 700, 5.0)):
        cmf = _cmfs_at(tuple(np.asarray(wl, np.float64).tolist()))
        assert np.array_equal(cmfs_matrix(wl), cmf / cmf[:, 1].sum())
