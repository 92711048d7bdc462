"""Spectral resampling: matrices, accuracy, coverage errors, cube application."""

import warnings

import numpy as np
import pytest
import spectral

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.synthesis.resample import (RESAMPLING_METHODS, PartialCoverageWarning, apply_matrix,
                                     default_fwhm, parse_bands, resample_cube,
                                     resampling_matrix)

RNG = np.random.default_rng(5)

#: Specim IQ-like band centres: 204 bands 397.32 … 1003.58 nm with slightly uneven spacing.
SPECIM_WL = np.linspace(397.32, 1003.58, 204) + 0.05 * np.sin(np.arange(204))


def test_gaussian_matrix_matches_spy_bandresampler():
    mine = resampling_matrix(SPECIM_WL, WAVELENGTHS_31, method="gaussian", dst_fwhm=10.0)
    spy = spectral.BandResampler(list(SPECIM_WL), list(WAVELENGTHS_31), None, [10.0] * 31).matrix
    assert not np.isnan(spy).any()
    np.testing.assert_allclose(mine, spy, atol=1e-12)


def test_gaussian_matrix_matches_spy_with_source_fwhm():
    fw = 2.5 + RNG.random(204)
    mine = resampling_matrix(SPECIM_WL, WAVELENGTHS_31, src_fwhm=fw, dst_fwhm=12.0)
    spy = spectral.BandResampler(list(SPECIM_WL), list(WAVELENGTHS_31), list(fw), [12.0] * 31)
    np.testing.assert_allclose(mine, spy.matrix, atol=1e-12)


@pytest.mark.parametrize("method", sorted(RESAMPLING_METHODS))
def test_flat_spectrum_stays_flat(method):
    m = resampling_matrix(SPECIM_WL, WAVELENGTHS_31, method=method)
    np.testing.assert_allclose(m @ np.full(204, 3.5), 3.5, rtol=1e-12)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=1e-12)
    assert (m >= 0).all()


def test_linear_spectrum_reproduced():
    line = 0.02 * SPECIM_WL - 3.0
    truth = 0.02 * WAVELENGTHS_31 - 3.0
    np.testing.assert_allclose(resampling_matrix(SPECIM_WL, method="linear") @ line, truth,
                               rtol=0, atol=1e-12)
    # The windowed methods are symmetric about the target only approximately
    # (source bands are not centred on the target), so a small tolerance.
    for method in ("gaussian", "box"):
        got = resampling_matrix(SPECIM_WL, method=method) @ line
        np.testing.assert_allclose(got, truth, rtol=0, atol=0.02 * 0.5)  # 0.5 nm shift


def test_gaussian_follows_a_smooth_spectrum():
    spec = np.exp(-0.5 * ((SPECIM_WL - 550) / 60) ** 2)
    got = resampling_matrix(SPECIM_WL) @ spec
    np.testing.assert_allclose(got, np.exp(-0.5 * ((WAVELENGTHS_31 - 550) / 60) ** 2), atol=5e-3)


@pytest.mark.parametrize("method", sorted(RESAMPLING_METHODS))
def test_unsorted_source_gives_the_same_result(method):
    perm = RNG.permutation(204)
    spec = RNG.random(204)
    m_sorted = resampling_matrix(SPECIM_WL, method=method)
    m_perm = resampling_matrix(SPECIM_WL[perm], method=method)
    np.testing.assert_allclose(m_perm @ spec[perm], m_sorted @ spec, rtol=1e-12)
    np.testing.assert_array_equal(m_perm, m_sorted[:, perm])


def test_unsorted_cube_gives_the_same_result():
    perm = RNG.permutation(204)
    data = RNG.random((3, 4, 204)).astype(np.float32)
    ref = resample_cube(SpectralCube(data, SPECIM_WL))
    with pytest.warns(UserWarning, match="not sorted"):
        shuffled = SpectralCube(data[:, :, perm], SPECIM_WL[perm])
    np.testing.assert_allclose(resample_cube(shuffled).data, ref.data, rtol=1e-6)


def test_target_without_coverage_names_the_band():
    with pytest.raises(InputError, match="380 nm"):
        resampling_matrix(SPECIM_WL, [380.0, 400.0])
    with pytest.raises(InputError, match="710 nm"):
        resampling_matrix(np.arange(400.0, 701.0, 5), [700.0, 710.0], method="linear")
    # A gap in the source bands: 600 nm sits in a hole.
    holey = np.concatenate([np.arange(400.0, 580, 3), np.arange(620.0, 700, 3)])
    with pytest.raises(InputError, match="600 nm"):
        resampling_matrix(holey, WAVELENGTHS_31, method="box")


def test_partially_covered_target_warns():
    src = np.arange(404.0, 720.0, 2.0)  # starts late: the 400 nm window is mostly empty
    with pytest.warns(PartialCoverageWarning, match="400 nm"):
        resampling_matrix(src, [400.0, 450.0], src_fwhm=2.0, dst_fwhm=10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        resampling_matrix(SPECIM_WL, WAVELENGTHS_31)


def test_bands_outside_every_window_are_ignored_and_never_read():
    m = resampling_matrix(SPECIM_WL)
    outside = (SPECIM_WL > 720) | (SPECIM_WL < 390)
    assert (m[:, outside] == 0).all()
    data = RNG.random((4, 5, 204)).astype(np.float32)
    data[:, :, outside] = np.nan  # would poison the result if read
    out = apply_matrix(data, m)
    assert np.isfinite(out).all()


def test_nan_in_a_used_band_raises():
    data = np.ones((3, 3, 204), np.float32)
    data[1, 1, 50] = np.nan
    with pytest.raises(InputError, match="NaN/Inf"):
        resample_cube(SpectralCube(data, SPECIM_WL, source="x.hdr"))


def test_resample_cube_chunking_and_metadata():
    data = (RNG.random((37, 11, 204)) * 4095).astype(np.uint16)
    cube = SpectralCube(data, SPECIM_WL, units="DN", integration_time_ms=12.5,
                        default_bands=(69, 52, 18), source="in.hdr")
    m = resampling_matrix(SPECIM_WL)
    want = data.astype(np.float64) @ m.T
    for chunk in (None, 1, 5, 100):
        out = resample_cube(cube, chunk_lines=chunk)
        assert out.data.dtype == np.float32 and out.shape == (37, 11, 31)
        np.testing.assert_allclose(out.data, want, rtol=1e-5)
    assert out.integration_time_ms == 12.5 and out.units == "DN"
    np.testing.assert_array_equal(out.wavelengths, WAVELENGTHS_31)
    np.testing.assert_array_equal(out.fwhm, 10.0)
    assert [out.wavelengths[b] for b in out.default_bands] == [600.0, 550.0, 450.0]
    assert out.metadata["resampling method"] == "gaussian"
    assert out.metadata["resampling fwhm"] == 10.0
    assert resample_cube(cube, method="linear").fwhm is None


def test_resample_memmap(tmp_path):
    data = RNG.random((20, 8, 204)).astype(np.float32)
    mm = np.lib.format.open_memmap(tmp_path / "c.npy", mode="w+", dtype=np.float32,
                                   shape=data.shape)
    mm[:] = data
    mm.flush()
    ro = np.load(tmp_path / "c.npy", mmap_mode="r")
    out = resample_cube(SpectralCube(ro, SPECIM_WL), chunk_lines=3)
    np.testing.assert_allclose(out.data, resample_cube(SpectralCube(data, SPECIM_WL)).data,
                               rtol=1e-6)


def test_bad_arguments():
    with pytest.raises(InputError, match="unknown resampling method"):
        resampling_matrix(SPECIM_WL, method="cubic")
    with pytest.raises(InputError, match="target FWHM"):
        resampling_matrix(SPECIM_WL, dst_fwhm=-1)
    with pytest.raises(InputError, match="duplicate"):
        resampling_matrix([400.0, 400.0, 410.0])
    with pytest.raises(InputError, match="source FWHM"):
        resampling_matrix(SPECIM_WL, src_fwhm=np.ones(3))


def test_parse_bands_and_default_fwhm():
    np.testing.assert_array_equal(parse_bands("400:700:10"), WAVELENGTHS_31)
    np.testing.assert_array_equal(parse_bands("450, 550,650"), [450, 550, 650])
    np.testing.assert_allclose(parse_bands("400:401:0.1").size, 11)
    for bad in ("700:400:10", "a:b:c", "400:700", "400:700:0"):
        with pytest.raises(InputError, match="cannot parse bands"):
            parse_bands(bad)
    np.testing.assert_allclose(default_fwhm([400, 402, 406, 407]), [2, 3, 2.5, 1])


@pytest.mark.parametrize("layout", ["bil", "bsq"])
def test_band_major_views_give_the_same_result(layout):
    # ENVI bil/bsq memmaps arrive as transposed views (samples axis fastest).
    data = (RNG.random((6, 9, 204)) * 4095).astype(">u2")  # big-endian, as some files are
    stored = (np.ascontiguousarray(data.transpose(0, 2, 1)) if layout == "bil"
              else np.ascontiguousarray(data.transpose(2, 0, 1)))
    view = stored.transpose(0, 2, 1) if layout == "bil" else stored.transpose(1, 2, 0)
    assert view.strides[2] > view.strides[1]
    m = resampling_matrix(SPECIM_WL)
    want = data.astype(np.float64) @ m.T
    for chunk in (None, 4):
        np.testing.assert_allclose(apply_matrix(view, m, chunk_lines=chunk), want, rtol=1e-5)
