"""Public SSR dataset readers: tiny files written in each dataset's exact layout."""

from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import scipy.io

from _checks import write_mat73
from mehs.errors import FormatError, InputError
from mehs.io.ssr_datasets import SourceOptions, read_source_cube
from mehs.rgb import WAVELENGTHS_31, spectra_to_linear_sRGB
from mehs.ssr.sources import detect_format, load_source

H, W = 12, 10


def _cube(n_bands=31, wl=WAVELENGTHS_31, seed=0, h=H, w=W):
    """ColorChecker reflectances under D65 (colour-science), one patch per pixel block, in [0, 1]."""
    import colour

    sds = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())
    ill = colour.SDS_ILLUMINANTS["D65"]
    refl = np.stack([np.interp(wl, sd.wavelengths, sd.values) for sd in sds])
    spd = np.interp(wl, ill.wavelengths, ill.values)
    rng = np.random.default_rng(seed)
    lab = rng.integers(0, 24, (h, w))
    cube = refl[lab] * spd / spd.max()
    return cube.astype(np.float32)


def _ntire_rgb8(cube: np.ndarray) -> np.ndarray:
    """An 8-bit RGB image made as the NTIRE 2022 code makes ARAD-1K's (``save_jpg``): the
    cube projected through a camera response (here the pseudo-HDR-RGB's), scaled so the
    mean is 18 % of 255, clipped and truncated to uint8, with no tone curve."""
    rgb = spectra_to_linear_sRGB(cube, WAVELENGTHS_31)
    rgb = rgb * (0.18 / rgb.mean()) * 255
    return rgb.clip(0, 255).astype(np.uint8)


def _jpg(path: Path, cube: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.ascontiguousarray(_ntire_rgb8(cube)[..., ::-1]),
                       [cv2.IMWRITE_JPEG_QUALITY, 98])


@pytest.fixture
def arad1k(tmp_path):
    """NTIRE 2022 layout: Train_Spec/*.mat (v7.3 cube/bands/norm_factor), Train_RGB/*.jpg,
    split_txt/{train,valid}_list.txt."""
    root = tmp_path / "ARAD_1K"
    cubes = {}
    for i, folder in ((1, "Train"), (2, "Train"), (3, "Valid")):
        sid = f"ARAD_1K_{i:04d}"
        cubes[sid] = _cube(seed=i)
        write_mat73(root / f"{folder}_Spec" / f"{sid}.mat",
                    {"cube": cubes[sid], "bands": WAVELENGTHS_31[None, :].astype(np.float64),
                     "norm_factor": np.array([[4095.0]])})
        _jpg(root / f"{folder}_RGB" / f"{sid}.jpg", cubes[sid])
    (root / "split_txt").mkdir()
    (root / "split_txt" / "train_list.txt").write_text("ARAD_1K_0001.mat\nARAD_1K_0002.mat\n")
    (root / "split_txt" / "valid_list.txt").write_text("ARAD_1K_0003.mat\n")
    return root, cubes


def test_arad1k_reads_shape_bands_scale_and_splits(arad1k):
    root, cubes = arad1k
    f = root / "Train_Spec" / "ARAD_1K_0001.mat"
    # the file really is stored as MATLAB does: (31, W, H) in HDF5
    with h5py.File(f, "r") as h:
        assert h["cube"].shape == (31, W, H)
    assert detect_format(root) == "arad1k"
    data, wl, info = read_source_cube("arad1k", f)
    assert data.shape == (H, W, 31) and data.dtype == np.float32
    np.testing.assert_array_equal(wl, WAVELENGTHS_31)
    np.testing.assert_array_equal(data, cubes["ARAD_1K_0001"])
    assert info["norm_factor"] == 4095.0 and info["options"]["scale"] == 1.0
    data2, wl2, info2 = read_source_cube("arad1k", f, SourceOptions(bands=(450.0, 550.0, 650.0),
                                                                     crop=(8, 6), scale=2.0))
    np.testing.assert_array_equal(wl2, [450, 550, 650])
    np.testing.assert_allclose(data2, 2 * cubes["ARAD_1K_0001"][2:10, 2:8][..., [5, 15, 25]])
    assert info2["options"] == {"bands": (450.0, 550.0, 650.0), "crop": (8, 6), "scale": 2.0,
                                "rgb_encoding": "auto"}
    ps = load_source(root)
    assert ps.splits == {"train": ["ARAD_1K_0001", "ARAD_1K_0002"], "val": ["ARAD_1K_0003"]}
    p = next(q for q in ps if q.id == "ARAD_1K_0003")
    assert p.ldr_path.name == "ARAD_1K_0003.jpg" and p.split == "val"
    ldr, hdr = p.rgb("ldr"), p.rgb("hdr")
    assert ldr.shape == hdr.shape == (H, W, 3)
    # the JPG, linearised and brought to the HDR scale, matches the pseudo-HDR-RGB's level
    # (per pixel JPEG's chroma subsampling blurs a 12×10 mosaic, so compare channel totals)
    np.testing.assert_allclose(ldr.sum(axis=(0, 1)), hdr.sum(axis=(0, 1)), rtol=0.1)


def test_arad1k_errors_name_the_file_and_the_key(arad1k, tmp_path):
    root, cubes = arad1k
    bad = write_mat73(tmp_path / "bad" / "ARAD_1K_0009.mat",
                      {"hsi": cubes["ARAD_1K_0001"], "bands": WAVELENGTHS_31[None, :]})
    with pytest.raises(FormatError, match="'cube'") as e:
        read_source_cube("arad1k", bad)
    assert str(bad) in str(e.value) and "hsi" in str(e.value)
    src = (root / "Train_Spec" / "ARAD_1K_0001.mat").read_bytes()
    trunc = tmp_path / "trunc" / "ARAD_1K_0001.mat"
    trunc.parent.mkdir()
    trunc.write_bytes(src[: len(src) // 2])
    with pytest.raises(FormatError, match="truncated") as e:
        read_source_cube("arad1k", trunc)
    assert str(trunc) in str(e.value)
    nob = write_mat73(tmp_path / "nob" / "x.mat", {"cube": cubes["ARAD_1K_0001"]})
    with pytest.raises(FormatError, match="'bands'"):
        read_source_cube("arad1k", nob)
    with pytest.raises(InputError, match="not in the file"):
        read_source_cube("arad1k", root / "Train_Spec" / "ARAD_1K_0001.mat",
                         SourceOptions(bands=(405.0,)))


def test_arad_bgu_v5_and_icvl_v73(tmp_path):
    # NTIRE 2018/2020 BGU-HS files saved by MATLAB -v5 (scipy writes that layout natively)
    c1 = _cube(seed=4)
    root = tmp_path / "NTIRE2018" / "Train_Spectral"
    root.mkdir(parents=True)
    stored = np.round(c1 * 4095).astype(np.uint16)
    scipy.io.savemat(root / "BGU_HS_00001.mat", {"rad": stored,
                                                   "bands": WAVELENGTHS_31[None, :]})
    assert detect_format(root.parent) == "arad"
    data, wl, _ = read_source_cube("arad", root / "BGU_HS_00001.mat", SourceOptions(scale=1 / 4095))
    assert data.shape == (H, W, 31)
    np.testing.assert_allclose(data, stored / 4095, rtol=1e-6)
    with pytest.raises(FormatError, match="no variable 'cube'.*variables: bands, rad"):
        read_source_cube("arad1k", root / "BGU_HS_00001.mat")  # has rad, not cube
    # ICVL: v7.3, 'rad' and 'bands' (its bands run 400..700 in 10 nm)
    c2 = _cube(seed=5, h=7, w=9) * 3000
    icvl = tmp_path / "icvl"
    write_mat73(icvl / "4cam_0411-1640-1.mat", {"rad": c2.astype(np.float64),
                                                "bands": WAVELENGTHS_31[:, None]})
    assert detect_format(icvl) == "icvl"
    ps = load_source(icvl)
    data, wl = ps[0].hs_array()
    assert data.shape == (7, 9, 31) and ps.splits == {}
    np.testing.assert_allclose(data, c2, rtol=1e-6)


def _cave(root: Path, name: str, cube: np.ndarray) -> Path:
    d = root / f"{name}_ms" / f"{name}_ms"
    d.mkdir(parents=True)
    for b in range(cube.shape[2]):
        assert cv2.imwrite(str(d / f"{name}_ms_{b + 1:02d}.png"),
                           np.round(cube[..., b] * 65535).astype(np.uint16))
    return d


def test_cave_folder_of_16_bit_pngs(tmp_path):
    c = _cube(seed=6)
    d = _cave(tmp_path / "cave", "balloons", c)
    _cave(tmp_path / "cave", "beads", _cube(seed=7))
    assert detect_format(tmp_path / "cave") == "cave"
    ps = load_source(tmp_path / "cave")
    assert sorted(p.id for p in ps) == ["balloons", "beads"]
    data, wl, info = read_source_cube("cave", d)
    assert data.shape == (H, W, 31) and info["bit_depth"] == 16
    np.testing.assert_array_equal(wl, WAVELENGTHS_31)
    np.testing.assert_allclose(data, np.round(c * 65535) / 65535, atol=1e-7)
    (d / "balloons_ms_17.png").unlink()
    with pytest.raises(FormatError, match="_17") as e:
        read_source_cube("cave", d)
    assert str(d) in str(e.value)
    (d / "balloons_ms_17.png").write_bytes((d / "balloons_ms_16.png").read_bytes()[:40])
    with pytest.raises(FormatError, match="truncated"):
        read_source_cube("cave", d)


def test_kaust_h5(tmp_path):
    wl34 = np.arange(400.0, 731.0, 10.0)
    c = _cube(34, wl34, seed=8)
    root = tmp_path / "kaust"
    root.mkdir()
    with h5py.File(root / "scene_01.h5", "w") as f:  # numpy order, bands stored
        f["img"] = c
        f["bands"] = wl34
    assert detect_format(root) == "kaust"
    data, wl, info = read_source_cube("kaust", root / "scene_01.h5")
    assert data.shape == (H, W, 31) and wl[0] == 400 and wl[-1] == 700  # 710–730 dropped
    np.testing.assert_array_equal(data, c[..., :31])
    data, wl, _ = read_source_cube("kaust", root / "scene_01.h5", SourceOptions(bands="all"))
    assert data.shape == (H, W, 34)
    # MATLAB-written (v7.3, column-major, no bands): the KAUST default 400:730:10
    write_mat73(root / "scene_02.h5", {"img": c})
    data, wl, info = read_source_cube("kaust", root / "scene_02.h5", SourceOptions(bands="all"))
    np.testing.assert_array_equal(data, c)
    assert info["matlab_order"] and "default" in info["bands_from"]
    with h5py.File(root / "bad.h5", "w") as f:
        f["mask"] = np.zeros((4, 4))
    with pytest.raises(FormatError, match="no 3-D image dataset") as e:
        read_source_cube("kaust", root / "bad.h5")
    assert "bad.h5" in str(e.value) and "mask" in str(e.value)


def test_cli_evaluate_and_train_baseline_read_arad1k(arad1k, tmp_path, capsys):
    from mehs.cli import main

    root, _ = arad1k
    assert main(["train-baseline", str(root), "--out", str(tmp_path / "reg.npz"),
                 "--samples", "200", "--format", "arad1k"]) == 0
    assert "2 scenes (train" in capsys.readouterr().out
    out = tmp_path / "ev"
    assert main(["evaluate", str(root), "--models", f"smits,{tmp_path / 'reg.npz'}",
                 "--input", "hdr,ldr", "--preprocess", "off", "--split", "val",
                 "--hs-crop", "8x8", "--out", str(out)]) == 0
    import json

    doc = json.loads((out / "evaluation.json").read_text())
    assert doc["config"]["n_scenes"] == 1
    rows = doc["rows"] if "rows" in doc else doc["results"]
    assert {r["model"] for r in rows} >= {"smits", "regression"}
    assert all(r["sam"] is not None and r["sam"] < 30 for r in rows)


def test_train_ssr_lists_arad1k_training_pairs(arad1k):
    pytest.importorskip("torch")
    from mehs.cli.train_ssr import _splits, load_training_pairs

    root, cubes = arad1k
    assert _splits(root) == ("train", "val")
    pairs, wl = load_training_pairs(root, split="train")
    assert len(pairs) == 2 and wl.size == 31


def test_detection_survives_one_truncated_file(arad1k):
    root, _ = arad1k
    first = sorted(root.rglob("*.mat"))[0]
    first.write_bytes(first.read_bytes()[:600])  # a broken download, sorted first
    assert detect_format(root) == "arad1k"
    ps = load_source(root)
    with pytest.raises(FormatError, match="truncated") as e:
        next(p for p in ps if p.hs_path == first).hs_array()
    assert str(first) in str(e.value)


@pytest.mark.parametrize("content", [b"", b"MATLAB 5.0 MAT-file".ljust(100, b" ")],
                         ids=["empty", "short-v5"])
def test_empty_or_short_mat_files_raise_a_format_error_naming_the_file(tmp_path, content):
    """An interrupted download (0 bytes, or a v5 header cut short) is a FormatError naming the
    file, not scipy's MatReadError / IndexError; format detection skips it."""
    bad = tmp_path / "Train_Spec" / "ARAD_1K_0001.mat"
    bad.parent.mkdir()
    bad.write_bytes(content)
    with pytest.raises(FormatError) as e:
        read_source_cube("arad1k", bad)
    assert str(bad) in str(e.value)
    write_mat73(tmp_path / "Train_Spec" / "ARAD_1K_0002.mat",
                {"cube": _cube(), "bands": WAVELENGTHS_31[None, :]})
    assert detect_format(tmp_path) == "arad1k"


def test_complex_or_text_variables_are_refused_naming_the_file(tmp_path):
    cplx = tmp_path / "c.mat"
    scipy.io.savemat(cplx, {"rad": _cube().astype(np.complex64), "bands": WAVELENGTHS_31})
    with pytest.raises(FormatError, match="real numbers") as e:
        read_source_cube("icvl", cplx)
    assert str(cplx) in str(e.value)
    txt = write_mat73(tmp_path / "t.mat", {"cube": _cube(), "bands": WAVELENGTHS_31[None, :]})
    with h5py.File(txt, "r+") as f:
        del f["bands"]
        f["bands"] = np.bytes_("400:700")
    with pytest.raises(FormatError, match="'bands' must be numbers"):
        read_source_cube("arad1k", txt)


def test_ntire_rgb_images_are_read_as_linear_and_others_as_srgb(tmp_path):
    """NTIRE 2020's ``*_clean.png`` (and 2022's JPGs) are camera projections scaled to 8 bits
    without a tone curve: read linearly, the LDR input is the HDR one up to exposure and
    quantisation; decoded as sRGB (as before) its ratio to the HDR varied 0.4–2×."""
    root = tmp_path / "NTIRE2020"
    cube = _cube(seed=4, h=24, w=20)
    write_mat73(root / "NTIRE2020_Train_Spectral" / "ARAD_HS_0001.mat",
                {"cube": cube, "bands": WAVELENGTHS_31[None, :].astype(np.float64)})
    png = root / "NTIRE2020_Train_Clean" / "ARAD_HS_0001_clean.png"
    png.parent.mkdir(parents=True)
    assert cv2.imwrite(str(png), np.ascontiguousarray(_ntire_rgb8(cube)[..., ::-1]))
    assert detect_format(root) == "arad1k"

    def ratio(opts):
        p = load_source(root, options=opts)[0] if opts else load_source(root)[0]
        ldr, hdr = p.rgb("ldr"), p.rgb("hdr")
        ok = (ldr * p.info["ldr_exposure_used"] > 20 / 255) & (ldr < 0.9 * ldr.max())
        return ldr[ok] / hdr[ok], p.info["ldr_encoding"]

    r, enc = ratio(None)
    assert enc == "linear"
    np.testing.assert_allclose(r, np.median(r), rtol=0.03)         # 8-bit truncation only
    r, enc = ratio(SourceOptions(rgb_encoding="srgb"))
    assert enc == "srgb" and r.max() / r.min() > 1.5
    with pytest.raises(InputError, match="rgb_encoding"):
        SourceOptions(rgb_encoding="gamma")
    # CAVE's RGB renderings stay sRGB unless told otherwise
    assert SourceOptions().rgb_encoding_for("cave") == "srgb"
    assert SourceOptions(rgb_encoding="linear").rgb_encoding_for("cave") == "linear"


def test_auto_split_scores_the_validation_list_when_there_is_no_test_split(arad1k, tmp_path):
    """No test split (ARAD-1K: the official validation list is the paper's test set,
    §3.6.1): ``--split auto`` scores the val scenes, not every scene (training included)."""
    import json

    from mehs.cli import main

    root, _ = arad1k
    out = tmp_path / "ev"
    assert main(["evaluate", str(root), "--models", "smits", "--input", "hdr",
                 "--preprocess", "off", "--hs-crop", "8x8", "--out", str(out)]) == 0
    assert json.loads((out / "evaluation.json").read_text())["config"]["n_scenes"] == 1


def test_kaust_cube_with_a_side_as_long_as_its_band_list_is_not_guessed(tmp_path):
    """(34 bands, 34 lines, 20 samples): the last axis was taken for the bands, reading the
    cube sideways; a band axis at one end only is still found."""
    wl34 = np.arange(400.0, 731.0, 10.0)
    with h5py.File(tmp_path / "a.h5", "w") as f:
        f["img"] = np.zeros((34, 20, 34), np.float32)      # B, H, W with W = B
        f["bands"] = wl34
    with pytest.raises(FormatError, match="more than one axis"):
        read_source_cube("kaust", tmp_path / "a.h5", SourceOptions(bands="all"))
    cube = np.random.default_rng(0).random((34, 34, 20)).astype(np.float32)   # B, H, W
    with h5py.File(tmp_path / "b.h5", "w") as f:
        f["img"] = cube
        f["bands"] = wl34
    data, _, _ = read_source_cube("kaust", tmp_path / "b.h5", SourceOptions(bands="all"))
    np.testing.assert_array_equal(data, np.moveaxis(cube, 0, -1))
