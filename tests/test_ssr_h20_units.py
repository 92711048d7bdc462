"""SSR pairs of a dataset are in the dataset's unit, whatever power of two ``mehs build``
stored each scene with (``quality.radiance_scale``): checked against the input spectra
(truth), colour-science's RGB of them, and files written in the public formats by hand."""

import json

import numpy as np
import pytest

from _checks import colour_srgb, ohta_chart
from mehs.cube import SpectralCube
from mehs.dataset.build import build_from_hs
from mehs.errors import FormatError
from mehs.io.envi import write_envi
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.data import load_pairs
from mehs.ssr.metrics import rmse

UNIT = "W sr-1 m-2 nm-1"


@pytest.fixture(scope="module")
def three_levels(tmp_path_factory):
    """One dataset of the same chart dim (lifted 2^k), ordinary, and bright (lowered)."""
    root = tmp_path_factory.mktemp("units")
    levels = {"dim": 1e-5, "mid": 1.0, "bright": 1e5}
    for name, lv in levels.items():
        write_envi(root / "in" / f"{name}.hdr",
                   SpectralCube(ohta_chart(lv), WAVELENGTHS_31, units=UNIT))
    build_from_hs([root / "in"], root / "ds", workers=1, progress=False)
    return root / "ds", levels


def test_dataset_pairs_share_one_unit_whatever_the_stored_scale(three_levels):
    ds, levels = three_levels
    doc = json.loads((ds / "manifest.json").read_text())
    scales = {s["id"]: s["quality"]["radiance_scale"] for s in doc["scenes"]}
    # the premise: the three scenes are stored with three different powers of two
    assert len({scales[k] for k in levels if k in scales}) == 3, scales
    pairs = {p.id: p for p in load_pairs(ds, include_failed=True)}
    for name, lv in levels.items():
        p = pairs[name]
        truth = ohta_chart(lv)
        hs, wl = p.hs_array()
        np.testing.assert_allclose(wl, WAVELENGTHS_31)
        # exact: the stored factor is a power of two
        np.testing.assert_array_equal(hs, truth)
        ref = colour_srgb(truth)
        ok = ref > 1e-4 * ref.max()
        rel = np.abs(p.hdr_rgb() - ref)[ok] / ref[ok]
        assert rel.max() < 2 ** -9, (name, rel.max())
        # the LDR image, linearised onto the HDR scale: 8-bit sRGB steps of well-exposed pixels
        ldr = p.ldr_rgb()
        lit = (ldr > 0.05 * ldr.max()) & (ldr < 0.9 * ldr.max()) & ok
        ratio = np.median(ldr[lit] / ref[lit])
        assert ratio == pytest.approx(1.0, rel=0.02), (name, ratio)


def test_rmse_is_in_the_dataset_unit(three_levels):
    """The same relative error on the same chart: RMSE scales with the light, not with 2^k."""
    ds, levels = three_levels
    pairs = {p.id: p for p in load_pairs(ds, include_failed=True)}
    got = {}
    for name, lv in levels.items():
        hs, _ = pairs[name].hs_array()
        got[name] = rmse(hs * np.float32(1.01), hs) / lv
    assert got["dim"] == pytest.approx(got["mid"], rel=1e-4)
    assert got["bright"] == pytest.approx(got["mid"], rel=1e-4)


def _hand_scene(root, scale, *, header_scale=None, exr_scale=None, noise=None):
    """hs.hdr (SPy), hdr_rgb.exr (OpenEXR) and manifest.json written by hand."""
    import OpenEXR
    import spectral.io.envi as envi

    rng = np.random.default_rng(3)
    data = rng.uniform(0.5, 2.0, (4, 5, 31)).astype(np.float32) * np.float32(scale)
    meta = {"wavelength": [str(w) for w in WAVELENGTHS_31], "interleave": "bil"}
    if header_scale is not None:
        meta["mehs radiance scale"] = repr(header_scale)
    (root / "s").mkdir(parents=True)
    envi.save_image(str(root / "s" / "hs.hdr"), data, dtype=np.float32, ext=".dat",
                    metadata=meta, interleave="bil", force=True)
    rgb = np.ascontiguousarray(data[:, :, [20, 12, 5]]).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if exr_scale is not None:
        header["mehsRadianceScale"] = float(exr_scale)
    with OpenEXR.File(header, {"RGB": rgb}) as f:
        f.write(str(root / "s" / "hdr_rgb.exr"))
    quality = {"radiance_scale": scale}
    if noise is not None:
        quality["noise_model"] = noise
    doc = {"format": "mehs-dataset/1", "splits": {},
           "scenes": [{"id": "s", "status": "pass", "quality": quality,
                       "files": {"hs": "s/hs.hdr", "hdr_rgb": "s/hdr_rgb.exr"}}]}
    (root / "manifest.json").write_text(json.dumps(doc))
    return data, rgb


def test_files_of_another_build_are_refused_naming_the_file(tmp_path):
    _, rgb = _hand_scene(tmp_path, 0.25, header_scale=0.5, exr_scale=0.25)
    (p,) = load_pairs(tmp_path, verify="none")
    with pytest.raises(FormatError, match="radiance scale") as err:
        p.hs_array()
    assert "hs.hdr" in str(err.value)
    # its partner agrees with the manifest and is served
    np.testing.assert_allclose(p.hdr_rgb(), rgb / 0.25, rtol=1e-6)


def test_a_manifest_scale_alone_is_divided_out(tmp_path):
    """A set whose files carry no header scale (older builds, other tools): the manifest's."""
    data, rgb = _hand_scene(tmp_path, 8.0)
    (p,) = load_pairs(tmp_path, verify="none")
    np.testing.assert_array_equal(p.hs_array()[0], data / 8)
    np.testing.assert_allclose(p.hdr_rgb(), rgb / 8, rtol=1e-6)


def test_the_mrae_floor_follows_the_unit(tmp_path):
    """10σ of a band noise model recorded for the stored values: in the dataset's unit it is
    σ/scale (σ² = zero·s² + shot·x·s + rel·(x·s)² for values x·s)."""
    zero, shot, rel = 0.04, 0.3, 0.01
    noise = {"format": "mehs-band-noise/1", "zero": [zero * 64] * 31, "shot": [shot * 8] * 31,
             "rel": [rel] * 31}
    from mehs.dataset.noisefloor import NOISE_MODEL_FORMAT

    noise["format"] = NOISE_MODEL_FORMAT
    data, _ = _hand_scene(tmp_path, 8.0, header_scale=8.0, noise=noise)
    (p,) = load_pairs(tmp_path, verify="none")
    gt, _ = p.hs_array()
    floor = p.mrae_floor(gt)
    sigma = np.sqrt(zero + shot * gt + rel * gt ** 2)
    np.testing.assert_allclose(floor, 10 * sigma, rtol=1e-5)
