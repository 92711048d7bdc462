"""The Harvard hyperspectral dataset (Chakrabarti & Zickler 2011) read and scored directly.

Scenes are written with ``scipy.io.savemat`` in the dataset's layout: one MATLAB v5
``.mat`` per scene with ``ref`` (rows × columns × 31, double, 420–720 nm) and ``lbl``
(rows × columns, 0 where objects moved during the scan). The radiance is colour-science's
ColorChecker reflectances under its D65; the masked region holds a motion smear (the
patch values scaled ×40) that must enter no metric.
"""

import numpy as np
import pytest
import scipy.io

colour = pytest.importorskip("colour")

from mehs.errors import FormatError  # noqa: E402
from mehs.io.ssr_datasets import SourceOptions, read_source_cube  # noqa: E402
from mehs.ssr.data import load_pairs  # noqa: E402
from mehs.ssr.scoring import evaluate  # noqa: E402
from mehs.ssr.sources import detect_format, load_source  # noqa: E402

WL = np.arange(420.0, 721.0, 10.0)
H, W = 24, 32


def radiance() -> np.ndarray:
    """ColorChecker N Ohta × D65 at 420:720:10, patches tiled over an ``H × W`` image."""
    d65 = colour.SDS_ILLUMINANTS["D65"]
    patches = [sd for sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()]
    spec = np.stack([np.interp(WL, sd.wavelengths, sd.values) *
                     np.interp(WL, d65.wavelengths, d65.values) / 100.0 for sd in patches])
    idx = (np.arange(H)[:, None] // 6 * 8 + np.arange(W)[None, :] // 4) % len(patches)
    return spec[idx]


def lbl() -> np.ndarray:
    m = np.ones((H, W), dtype=np.uint8)
    m[2:9, 20:29] = 0                     # a moving object
    return m


def write_scene(path, *, smear=True, label=True, ref=None):
    ref = radiance() if ref is None else ref
    if smear:
        ref = ref.copy()
        ref[lbl() == 0] *= 40.0
    d = {"ref": ref.astype(np.float64)}
    if label is True:
        d["lbl"] = lbl()
    elif label is not None:
        d["lbl"] = label
    scipy.io.savemat(str(path), d)        # MATLAB v5, as the dataset ships
    return path


def ratio_model(rgb):
    """A per-pixel model (each output pixel depends on its own RGB only)."""
    base = radiance().mean(axis=(0, 1))
    full = np.interp(np.arange(400.0, 701.0, 10.0), WL, base)
    return (rgb.sum(-1, keepdims=True) * full / full.sum()).astype(np.float32)


def test_reader_bands_and_detection(tmp_path):
    write_scene(tmp_path / "img1.mat")
    assert detect_format(tmp_path) == "harvard"
    cube, wl, info = read_source_cube("harvard", tmp_path / "img1.mat")
    np.testing.assert_array_equal(wl, np.arange(420.0, 701.0, 10.0))   # 29 bands in 400–700
    ref = scipy.io.loadmat(str(tmp_path / "img1.mat"))["ref"]
    np.testing.assert_allclose(cube, ref[..., :29].astype(np.float32))
    cube, wl, _ = read_source_cube("harvard", tmp_path / "img1.mat", SourceOptions(bands="all"))
    np.testing.assert_array_equal(wl, WL)
    assert cube.shape == (H, W, 31)


def test_moving_region_is_masked_and_enters_no_metric(tmp_path):
    clean, smeared = tmp_path / "clean", tmp_path / "smeared"
    clean.mkdir()
    smeared.mkdir()
    write_scene(clean / "img1.mat", smear=False)
    write_scene(smeared / "img1.mat", smear=True)
    pairs = load_pairs(smeared)
    assert pairs.manifest["source_format"] == "harvard"
    want = scipy.io.loadmat(str(smeared / "img1.mat"))["lbl"] != 0
    np.testing.assert_array_equal(pairs[0].valid((H, W)), want)
    scores = []
    for root in (clean, smeared):
        res = evaluate(root, [f"{__file__}:ratio_model"], preprocess="off", restore=False,
                       split=None, figures=0)
        row = res.rows[0]
        assert row["n_pixels"] == int(want.sum())
        scores.append([row[k] for k in ("sam", "mrae", "rmse", "psnr")])
    # the smear (×40 in the masked region) changes nothing: those pixels are not scored
    np.testing.assert_allclose(scores[0], scores[1], rtol=1e-6)


def test_central_crop_applies_to_the_mask(tmp_path):
    write_scene(tmp_path / "img1.mat")
    ps = load_source(tmp_path, "harvard", options=SourceOptions(crop=(12, 16)))
    cube, _ = ps[0].hs_array()
    assert cube.shape[:2] == (12, 16)
    np.testing.assert_array_equal(ps[0].valid(cube.shape[:2]), (lbl() != 0)[6:18, 8:24])


def test_lbl_missing_all_zero_or_misshapen(tmp_path):
    def folder(name, label):
        (tmp_path / name).mkdir()
        write_scene(tmp_path / name / "img1.mat", label=label)
        return load_source(tmp_path / name, "harvard")[0]

    # explicit format, no lbl: no mask, every pixel scored
    assert folder("none", None).valid((H, W)).all()
    with pytest.raises(FormatError, match="marks no pixel as usable"):
        folder("zeros", np.zeros((H, W), np.uint8)).valid((H, W))
    with pytest.raises(FormatError, match="the mask is 24×31, the cube 24×32"):
        folder("narrow", np.ones((H, W - 1), np.uint8)).valid((H, W))


def test_ref_with_other_than_31_bands_is_refused(tmp_path):
    write_scene(tmp_path / "img1.mat", ref=radiance()[..., :30], smear=False)
    with pytest.raises(FormatError, match="31 bands"):
        read_source_cube("harvard", tmp_path / "img1.mat")


def test_every_reader_format_is_a_cli_choice():
    # the CLI spells its choices out (a light import); a new reader must be listed there too
    from mehs.cli._sources import FORMAT_CHOICES
    from mehs.io.ssr_datasets import FORMATS

    assert set(FORMAT_CHOICES) == {"auto", *FORMATS}
