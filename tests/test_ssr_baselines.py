"""Baselines: vectorised Smits/Mallett against colour-science, regression fit/save/load."""

import json

import colour
import numpy as np
import pytest

from mehs.errors import FormatError, InputError
from mehs.rgb import WAVELENGTHS_31, XYZ_TO_SRGB, cmfs_matrix
from mehs.ssr.baselines import (RGB_to_spectra_Mallett2019, RGB_to_spectra_Smits1999,
                                RegressionModel, root_polynomial_features)
from mehs.ssr.models import load_model

W = WAVELENGTHS_31


def _colour_smits(rgb):
    return np.array([colour.recovery.RGB_to_sd_Smits1999(p)[W] for p in rgb.reshape(-1, 3)])


def test_smits_matches_colour_per_pixel_including_hdr_negative_and_ties():
    rng = np.random.default_rng(0)
    rgb = np.concatenate([
        rng.uniform(0, 1, (300, 3)),                 # display range
        rng.uniform(0, 1, (100, 3)) * 1e3,           # HDR, unclamped
        rng.normal(0.2, 0.5, (100, 3)),              # negatives (colour does not clamp)
        np.array([[0.5, 0.5, 0.5], [0.2, 0.2, 0.7], [0.7, 0.2, 0.7], [0.3, 0.9, 0.9],
                  [0, 0, 0], [1, 1, 1], [0.4, 0.1, 0.1]]),
    ])
    ours = RGB_to_spectra_Smits1999(rgb)
    np.testing.assert_allclose(ours, _colour_smits(rgb), rtol=0, atol=1e-6)
    # And relative to scale on the HDR block.
    hdr = rgb[300:400]
    np.testing.assert_allclose(RGB_to_spectra_Smits1999(hdr), _colour_smits(hdr), rtol=1e-9)


@pytest.mark.filterwarnings("ignore:.*not uniform")
def test_smits_resampling_equals_colours_align():
    sd = colour.recovery.RGB_to_sd_Smits1999(np.array([0.3, 0.6, 0.1]))
    aligned = sd.copy().align(colour.SpectralShape(400, 700, 10)).values
    np.testing.assert_allclose(RGB_to_spectra_Smits1999(np.array([0.3, 0.6, 0.1])), aligned,
                               atol=1e-12)


def test_smits_on_images_float32_and_equivariant():
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 5, (7, 9, 3)).astype(np.float32)
    out = RGB_to_spectra_Smits1999(img)
    assert out.shape == (7, 9, 31) and out.dtype == np.float32
    np.testing.assert_allclose(out.reshape(-1, 31), _colour_smits(img.astype(np.float64)),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(RGB_to_spectra_Smits1999(img * 8), out * 8, rtol=1e-5)


def test_mallett_matches_colour():
    rng = np.random.default_rng(2)
    rgb = rng.uniform(0, 1, (50, 3))
    ref = np.array([colour.recovery.RGB_to_sd_Mallett2019(p)[W] for p in rgb])
    np.testing.assert_allclose(RGB_to_spectra_Mallett2019(rgb), ref, atol=1e-12)


def test_root_polynomial_features_are_degree_one_homogeneous():
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 3, (20, 3))
    for d, nf in ((1, 3), (2, 6), (3, 13)):
        f = root_polynomial_features(x, d)
        assert f.shape == (20, nf)
        np.testing.assert_allclose(root_polynomial_features(7.5 * x, d), 7.5 * f, rtol=1e-12)
    with pytest.raises(InputError):
        root_polynomial_features(x, 4)


def _training_set(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    refl = np.stack([np.interp(W, sd.wavelengths, sd.values) for sd in
                     colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()])
    d65 = np.interp(W, colour.SDS_ILLUMINANTS["D65"].wavelengths,
                    colour.SDS_ILLUMINANTS["D65"].values)
    w = rng.dirichlet(np.ones(24) * 0.3, n)
    spectra = (w @ refl) * d65 / 100 * np.exp(rng.uniform(-4, 6, (n, 1)))
    rgb = np.maximum(spectra @ cmfs_matrix(W) @ XYZ_TO_SRGB.T, 0)
    return rgb, spectra


def test_regression_fit_recovers_training_spectra_better_than_smits_and_is_exposure_invariant():
    from mehs.ssr.luminance import restore_luminance
    from mehs.ssr.metrics import mrae, sam_deg

    rgb, spectra = _training_set()
    model = RegressionModel.fit(rgb[:2000], spectra[:2000], degree=2)
    test_rgb, test_gt = rgb[2000:, None, :].astype(np.float32), spectra[2000:, None, :]
    pred = restore_luminance(model(test_rgb), test_rgb, W)
    smits = restore_luminance(RGB_to_spectra_Smits1999(test_rgb), test_rgb, W)
    assert sam_deg(pred, test_gt) < 0.7 * sam_deg(smits, test_gt)
    assert mrae(pred, test_gt) < mrae(smits, test_gt)
    np.testing.assert_allclose(model(test_rgb * 100), model(test_rgb) * 100, rtol=1e-4)


def test_regression_save_load_roundtrip(tmp_path):
    rgb, spectra = _training_set(500)
    model = RegressionModel.fit(rgb, spectra, degree=3, info={"note": "x"})
    for name in ("m.npz", "m.json"):
        p = model.save(tmp_path / name)
        back = load_model(str(p))
        assert isinstance(back, RegressionModel) and back.degree == 3
        np.testing.assert_allclose(back.matrix, model.matrix)
        assert back.info["note"] == "x"
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="bad.npz"):
        RegressionModel.load(tmp_path / "bad.npz")
    (tmp_path / "other.json").write_text(json.dumps({"format": "x"}))
    with pytest.raises(FormatError, match="other.json"):
        RegressionModel.load(tmp_path / "other.json")
    with pytest.raises(InputError, match="missing.npz"):
        load_model(str(tmp_path / "missing.npz"))


def test_regression_needs_enough_data():
    with pytest.raises(InputError, match="usable training pixels"):
        RegressionModel.fit(np.zeros((100, 3)), np.ones((100, 31)))
