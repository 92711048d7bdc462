"""The KAIST hyperspectral dataset (Choi et al. 2017) and its 28-band CASSI cubes, read directly.

Scenes are written in the public layouts (see :mod:`mehs.io.ssr_kaist` for the code they come
from): a KAIST ``sceneNN_reflectance.exr`` written with the OpenEXR package, channels
``R``, ``G``, ``B`` and ``w420nm`` … ``w720nm`` (half floats, as names are all the file
records); the CASSI benchmarks' ``Truth/sceneNN.mat`` (``img``, MATLAB v5) and
``KAIST_CVPR2021/N.mat`` (``HSI``, here as v7.3). The spectra are colour-science's ColorChecker
reflectances.
"""

import numpy as np
import pytest
import scipy.io

colour = pytest.importorskip("colour")
OpenEXR = pytest.importorskip("OpenEXR")

from _checks import write_mat73  # noqa: E402

from mehs.errors import FormatError, InputError  # noqa: E402
from mehs.io.ssr_datasets import SourceOptions, read_source_cube  # noqa: E402
from mehs.io.ssr_kaist import CASSI28_BANDS  # noqa: E402
from mehs.ssr.data import load_pairs  # noqa: E402
from mehs.ssr.scoring import evaluate  # noqa: E402
from mehs.ssr.sources import detect_format, load_source  # noqa: E402

WL = np.arange(420.0, 721.0, 10.0)
H, W = 12, 16


def reflectance(wl=WL) -> np.ndarray:
    """ColorChecker N Ohta reflectances at ``wl``, patches tiled over an ``H × W`` image."""
    patches = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())
    spec = np.stack([np.interp(wl, sd.wavelengths, sd.values) for sd in patches])
    idx = (np.arange(H)[:, None] // 4 * 4 + np.arange(W)[None, :] // 4) % len(patches)
    return spec[idx]


def write_kaist(path, cube=None, names=None, *, half=True, rgb=True):
    """A KAIST EXR: one ``w<λ>nm`` channel per band (+ R, G, B), OpenEXR's own writer."""
    cube = reflectance() if cube is None else cube
    names = [f"w{int(w)}nm" for w in WL] if names is None else names
    dt = np.float16 if half else np.float32
    chans = {n: np.ascontiguousarray(cube[..., i], dtype=dt) for i, n in enumerate(names)}
    if rgb:
        chans.update({c: np.full(cube.shape[:2], 0.25, dtype=dt) for c in "RGB"})
    path.parent.mkdir(parents=True, exist_ok=True)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 chans).write(str(path))
    return path


def flat_model(rgb):
    """A per-pixel model with 400:700:10 outputs."""
    return np.repeat(rgb.mean(-1, keepdims=True), 31, axis=-1).astype(np.float32)


# --------------------------------------------------------------------------- KAIST EXR
@pytest.mark.parametrize("half", [True, False])
def test_kaist_exr_bands_values_and_detection(tmp_path, half):
    write_kaist(tmp_path / "scene01_reflectance.exr", half=half)
    assert detect_format(tmp_path) == "kaist"
    want = reflectance().astype(np.float16 if half else np.float32).astype(np.float32)
    cube, wl, info = read_source_cube("kaist", tmp_path / "scene01_reflectance.exr")
    np.testing.assert_array_equal(wl, np.arange(420.0, 701.0, 10.0))   # 29 bands in 400–700
    np.testing.assert_array_equal(cube, want[..., :29])
    assert info["ignored_channels"] == ["B", "G", "R"]
    cube, wl, _ = read_source_cube("kaist", tmp_path / "scene01_reflectance.exr",
                                   SourceOptions(bands="all"))
    np.testing.assert_array_equal(wl, WL)
    np.testing.assert_array_equal(cube, want)


def test_kaist_bands_follow_the_names_not_the_storage_order(tmp_path):
    # EXR stores channels sorted by name; a decimal centre sorts out of wavelength order
    # ('w425.5nm' < 'w425nm' by name), so only the names give the bands' order
    wl = np.array([420.0, 425.0, 425.5, 430.0])
    names = ["w420nm", "w425nm", "w425.5nm", "w430nm"]
    cube = np.broadcast_to(wl / 1000.0, (H, W, 4))
    write_kaist(tmp_path / "s.exr", cube, names, half=False)
    got, bands, _ = read_source_cube("kaist", tmp_path / "s.exr")
    np.testing.assert_array_equal(bands, wl)
    np.testing.assert_allclose(got[0, 0], (wl / 1000.0).astype(np.float32))


def test_kaist_folder_is_listed_scored_and_rendered(tmp_path):
    root = tmp_path / "kaist"
    for i in (1, 2):
        write_kaist(root / f"scene{i:02d}_reflectance.exr", reflectance() * (0.5 * i))
    pairs = load_pairs(root)
    assert pairs.manifest["source_format"] == "kaist"
    assert [p.id for p in pairs] == ["scene01_reflectance", "scene02_reflectance"]
    rgb = pairs[0].hdr_rgb()
    assert rgb.shape == (H, W, 3) and rgb.max() > 0
    assert pairs[0].ldr_rgb().shape == (H, W, 3)    # rendered: the EXR's R, G, B are unused
    res = evaluate(root, [f"{__file__}:flat_model"], preprocess="off", restore=False,
                   split=None, figures=0)
    assert len(res.rows) == 2 and all(np.isfinite(r["mrae"]) for r in res.rows)


def test_rgb_and_spectral_exrs_of_other_layouts_are_not_kaist(tmp_path):
    from mehs.io.exr import write_exr_rgb, write_exr_spectral

    rgb, fichet = tmp_path / "rgb", tmp_path / "fichet"
    rgb.mkdir()
    fichet.mkdir()
    write_exr_rgb(rgb / "a.exr", np.ones((4, 4, 3)))
    write_exr_spectral(fichet / "a.exr", np.ones((4, 4, 31), np.float32),
                       np.arange(400.0, 701.0, 10.0))
    assert detect_format(rgb) is None
    assert detect_format(fichet) is None


def test_kaist_layout_errors_name_the_problem(tmp_path):
    from mehs.io.exr import write_exr_rgb

    write_exr_rgb(tmp_path / "rgb.exr", np.ones((4, 4, 3)))
    with pytest.raises(FormatError, match=r"no KAIST spectral channel.*\['B', 'G', 'R'\]"):
        read_source_cube("kaist", tmp_path / "rgb.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr at all")
    with pytest.raises(FormatError, match="not an OpenEXR file"):
        read_source_cube("kaist", tmp_path / "bad.exr")
    write_kaist(tmp_path / "dup.exr", reflectance()[..., :3], ["w420nm", "w420.0nm", "w430nm"])
    with pytest.raises(FormatError, match="name the same wavelength"):
        read_source_cube("kaist", tmp_path / "dup.exr")


def test_a_truncated_download_neither_hides_the_format_nor_reads(tmp_path):
    good = write_kaist(tmp_path / "scene02_reflectance.exr").read_bytes()
    (tmp_path / "scene01_reflectance.exr").write_bytes(good[:len(good) // 2])
    assert detect_format(tmp_path) == "kaist"
    with pytest.raises(FormatError, match="cannot read the OpenEXR file"):
        read_source_cube("kaist", tmp_path / "scene01_reflectance.exr")


# --------------------------------------------------------------------------- CASSI 28 bands
def test_cassi28_truth_img_v5_and_kaist_cvpr2021_hsi_v73(tmp_path):
    cube = reflectance(CASSI28_BANDS)
    truth = tmp_path / "TSA_simu_data" / "Truth"
    truth.mkdir(parents=True)
    scipy.io.savemat(str(truth / "scene01.mat"), {"img": cube})          # as sio.loadmat reads it
    assert detect_format(truth) == "cassi28"
    got, wl, info = read_source_cube("cassi28", truth / "scene01.mat")
    np.testing.assert_array_equal(wl, CASSI28_BANDS)                     # all 28 in 400–700
    np.testing.assert_allclose(got, cube.astype(np.float32))
    assert info["variable"] == "img"

    cvpr = tmp_path / "KAIST_CVPR2021"
    write_mat73(cvpr / "1.mat", {"HSI": cube.astype(np.float32)})
    assert detect_format(cvpr) == "cassi28"
    got, wl, info = read_source_cube("cassi28", cvpr / "1.mat")
    assert got.shape == (H, W, 28) and info["variable"] == "HSI"
    np.testing.assert_allclose(got, cube.astype(np.float32))
    # the bands are off the 10 nm grid: a 400:700:10 model is refused by name, not scored
    with pytest.raises(InputError, match=r"lack \[453.5, 457.5"):
        evaluate(cvpr, [f"{__file__}:flat_model"], preprocess="off", restore=False,
                 split=None, figures=0)


def test_cassi28_is_not_detected_from_other_img_variables(tmp_path):
    scipy.io.savemat(str(tmp_path / "scene1.mat"), {"img": reflectance()})   # 31 bands
    assert detect_format(tmp_path) is None
    other = tmp_path / "cave28"
    other.mkdir()
    scipy.io.savemat(str(other / "scene1.mat"),
                     {"img_expand": (reflectance(CASSI28_BANDS) * 65535).astype(np.uint16)})
    assert detect_format(other) is None
    with pytest.raises(FormatError, match=r"no 'img' or 'HSI'.*img_expand"):
        read_source_cube("cassi28", other / "scene1.mat")
    with pytest.raises(FormatError, match="28 bands"):
        read_source_cube("cassi28", tmp_path / "scene1.mat")


def test_load_source_lists_cassi28_scenes(tmp_path):
    for i in (1, 2):
        scipy.io.savemat(str(tmp_path / f"scene{i:02d}.mat"), {"img": reflectance(CASSI28_BANDS)})
    ps = load_source(tmp_path)
    assert ps.manifest["source_format"] == "cassi28" and len(ps) == 2
    data, wl = ps[0].hs_array()
    assert data.shape == (H, W, 28) and wl.size == 28


def test_cassi28_coded_aperture_files_are_not_scenes(tmp_path):
    # MST's layout: TSA_simu_data/mask.mat beside Truth/scene01.mat … scene10.mat
    root = tmp_path / "TSA_simu_data"
    (root / "Truth").mkdir(parents=True)
    scipy.io.savemat(str(root / "mask.mat"), {"mask": np.ones((H, W))})
    scipy.io.savemat(str(root / "mask_3d_shift.mat"), {"mask_3d_shift": np.ones((H, W + 54, 28))})
    for i in (1, 2):
        scipy.io.savemat(str(root / "Truth" / f"scene{i:02d}.mat"),
                         {"img": reflectance(CASSI28_BANDS)})
    assert detect_format(root) == "cassi28"
    ps = load_source(root)
    assert [p.id for p in ps] == ["scene01", "scene02"]
