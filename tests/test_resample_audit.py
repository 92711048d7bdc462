"""Resampling audit: bad bands, no-data markers, default bands, options and provenance.

Outside truths used here: ENVI's ``bbl`` flags bands to be left out of processing and
``data ignore value`` marks samples that are no data (NV5 *ENVI Header Files*); SPy's
``BandResampler`` built on the good bands only is what a resampling that leaves the bad
bands out must give.
"""

import warnings

import numpy as np
import pytest
import spectral
from spectral.algorithms.resampling import build_fwhm

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS as WL
from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.synthesis.resample import (PartialCoverageWarning, parse_bands, resample_cube,
                                     resampling_matrix)

RNG = np.random.default_rng(11)


def _bbl(bad_idx, n=204):
    bbl = ["1"] * n
    for i in bad_idx:
        bbl[i] = "0"
    return bbl


def _spy_on_good_bands(good):
    # SPy's widths come from the spacing of *all* the sensor's bands (a flagged band is
    # still there); its matrix is then built on the good bands alone.
    fw = build_fwhm(list(WL))
    return spectral.BandResampler(list(WL[good]), list(WAVELENGTHS_31),
                                  [fw[i] for i in np.flatnonzero(good)], [10.0] * 31).matrix


@pytest.mark.parametrize("fill", [1000.0, np.nan])
def test_bad_bands_are_left_out(fill):
    bad = int(np.argmin(np.abs(WL - 572.0)))  # inside the 570 nm window only
    spec = RNG.random(204).astype(np.float32)
    data = np.tile(spec, (2, 3, 1))
    data[:, :, bad] = fill  # a dead band: garbage or NaN
    out = resample_cube(SpectralCube(data, WL, metadata={"bbl": _bbl([bad])}, source="x.hdr"))
    good = np.ones(204, bool)
    good[bad] = False
    want = _spy_on_good_bands(good) @ spec[good].astype(np.float64)
    np.testing.assert_allclose(out.data[1, 2], want, rtol=2e-6)
    assert out.metadata["bbl"] == [1] * 31  # the good neighbours fill the 570 nm band


def test_target_reached_only_by_bad_bands_is_made_from_them_and_flagged():
    bad = np.flatnonzero((WL > 563) & (WL < 577))  # 566.21 .. 575.04 nm: all of 570's window
    data = np.ones((1, 2, 204), np.float32)
    data[:, :, bad] = 5.0
    cube = SpectralCube(data, WL, metadata={"bbl": _bbl(bad)})
    with pytest.warns(PartialCoverageWarning, match="570 nm"):
        out = resample_cube(cube)
    i570 = list(WAVELENGTHS_31).index(570.0)
    assert out.data[0, 0, i570] == pytest.approx(5.0)
    flagged = [int(w) for w, b in zip(out.wavelengths, out.metadata["bbl"]) if b == 0]
    assert flagged == [570]  # 560/580: mostly good bands; their bad edge is left out
    np.testing.assert_allclose(np.delete(out.data[0, 0], i570), 1.0, rtol=1e-6)


def test_a_target_mostly_in_bad_bands_is_flagged():
    # 557.39 .. 575.04 nm bad: 560 nm keeps one good band (554.45) at its edge, made from
    # it alone — an extrapolation, so flagged; 580 nm is mostly good and stays good.
    bad = np.flatnonzero((WL > 556) & (WL < 580))
    with pytest.warns(PartialCoverageWarning, match="570 nm"):
        out = resample_cube(SpectralCube(np.ones((1, 1, 204), np.float32), WL,
                                         metadata={"bbl": _bbl(bad)}))
    flagged = [int(w) for w, b in zip(out.wavelengths, out.metadata["bbl"]) if b == 0]
    assert flagged == [560, 570]


def test_resampling_matrix_exclude_matches_spy_on_good_bands():
    good = RNG.random(204) > 0.2
    m = resampling_matrix(WL, exclude=~good)
    np.testing.assert_allclose(m[:, good], _spy_on_good_bands(good), atol=1e-12)
    assert (m[:, ~good] == 0).all()
    lin = resampling_matrix(WL, method="linear", exclude=~good)
    line = 0.01 * WL + 2.0
    np.testing.assert_allclose(lin @ line, 0.01 * WAVELENGTHS_31 + 2.0, atol=1e-12)
    assert (lin[:, ~good] == 0).all()


@pytest.mark.parametrize("ignore", [-9999.0, 0.0])
def test_data_ignore_value_samples_stay_no_data(ignore):
    spec = 1.0 + RNG.random(204).astype(np.float32)
    data = np.tile(spec, (2, 2, 1))
    data[0, 0, :] = ignore                 # a no-data pixel (a mosaic's border)
    hole = int(np.argmin(np.abs(WL - 500.0)))
    data[1, 1, hole] = ignore              # one missing sample
    cube = SpectralCube(data, WL, metadata={"data ignore value": f"{ignore:g}"})
    out = resample_cube(cube).data
    m = resampling_matrix(WL)
    assert (out[0, 0] == np.float32(ignore)).all()
    touched = m[:, hole] != 0
    assert touched.any()
    assert (out[1, 1, touched] == np.float32(ignore)).all()
    np.testing.assert_allclose(out[1, 1, ~touched], (m @ spec)[~touched], rtol=1e-5)
    np.testing.assert_allclose(out[0, 1], m @ spec, rtol=1e-5)


def test_nan_ignore_value_is_no_data_not_an_error():
    data = np.ones((2, 2, 204), np.float32)
    data[1, 0] = np.nan
    out = resample_cube(SpectralCube(data, WL, metadata={"data ignore value": "NaN"}))
    assert np.isnan(out.data[1, 0]).all() and (out.data[0] == pytest.approx(1.0))
    with pytest.raises(InputError, match="NaN/Inf"):  # without the marker: refused
        resample_cube(SpectralCube(data, WL))


def test_ignore_value_in_band_major_memmap_layout():
    data = 1.0 + RNG.random((3, 5, 204)).astype(np.float32)
    data[2, 4] = -1.0
    view = np.ascontiguousarray(data.transpose(0, 2, 1)).transpose(0, 2, 1)  # bil
    out = resample_cube(SpectralCube(view, WL, metadata={"data ignore value": "-1"}),
                        chunk_lines=2)
    assert (out.data[2, 4] == -1.0).all()
    np.testing.assert_allclose(out.data[:2], data[:2] @ resampling_matrix(WL).T, rtol=1e-5)


def test_bad_ignore_value_is_an_input_error():
    cube = SpectralCube(np.ones((1, 1, 204), np.float32), WL,
                        metadata={"data ignore value": "none"}, source="x.hdr")
    with pytest.raises(InputError, match="data ignore value"):
        resample_cube(cube)


def test_default_bands_outside_the_target_range_are_dropped():
    data = np.ones((1, 1, 204), np.float32)
    nir = int(np.argmin(np.abs(WL - 841.0)))
    cube = SpectralCube(data, WL, default_bands=(nir, 69, 18))
    assert resample_cube(cube).default_bands is None  # not a silent 700 nm red
    kept = resample_cube(SpectralCube(data, WL, default_bands=(69, 52, 18)))
    assert [kept.wavelengths[b] for b in kept.default_bands] == [600.0, 550.0, 450.0]


def test_parse_bands_refuses_non_finite_values():
    for bad in ("400:inf:10", "400:700:inf", "-inf:700:10", "400,nan"):
        with pytest.raises(InputError, match="cannot parse bands"):
            parse_bands(bad)


def test_micrometre_wavelengths_get_a_hint():
    with pytest.raises(InputError, match="micrometres"):
        resampling_matrix(WL / 1000.0)


def test_source_fwhm_provenance_is_recorded():
    data = np.ones((1, 1, 204), np.float32)
    assumed = resample_cube(SpectralCube(data, WL)).metadata["resampling source fwhm"]
    assert "assumed" in assumed
    given = resample_cube(SpectralCube(data, WL, fwhm=np.full(204, 7.0)))
    assert given.metadata["resampling source fwhm"] == "header"


def test_unsorted_target_with_per_band_fwhm_keeps_pairs():
    data = (1.0 + RNG.random((1, 2, 204))).astype(np.float32)
    cube = SpectralCube(data, WL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = resample_cube(cube, [700.0, 400.0, 550.0], fwhm=[12.0, 20.0, 15.0])
    np.testing.assert_array_equal(out.wavelengths, [400.0, 550.0, 700.0])
    np.testing.assert_array_equal(out.fwhm, [20.0, 15.0, 12.0])
    assert out.metadata["resampling fwhm"] == [20.0, 15.0, 12.0]
    ref = resample_cube(cube, [400.0, 550.0, 700.0], fwhm=[20.0, 15.0, 12.0])
    np.testing.assert_array_equal(out.data, ref.data)


def test_linear_matches_colour_and_refuses_what_colour_extrapolates():
    import colour

    v = RNG.random(204)
    want = colour.LinearInterpolator(WL, v)(WAVELENGTHS_31)
    np.testing.assert_allclose(resampling_matrix(WL, method="linear") @ v, want, atol=1e-12)
    short = WL[WL < 690]  # a sensor that ends below 700 nm
    with pytest.raises(InputError, match="690 nm, 700 nm"):
        resampling_matrix(short, method="linear")
