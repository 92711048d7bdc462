"""Harvard (Chakrabarti & Zickler 2011): the ``lbl`` polarity and ``calib.txt`` are options,
since public code disagrees and the readme could not be checked (audit h19, item 3)."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import scipy.io

from mehs.cli._sources import add_source_arguments, apply_source_arguments
from mehs.errors import FormatError, InputError
from mehs.io.ssr_datasets import SourceOptions, read_source_cube
from mehs.ssr.sources import load_source, remembered

WL = np.arange(420.0, 721.0, 10.0)
H, W = 6, 8


def _scene(root):
    """``ref`` = band index + 1 everywhere, ``lbl`` 0 on a 2×3 block, as the dataset ships
    them (MATLAB v5), in a sub-folder; ``calib.txt`` (31 factors) at the dataset root."""
    (root / "CZ_hsdb").mkdir(parents=True)
    ref = np.broadcast_to(np.arange(1.0, 32.0), (H, W, 31)).copy()
    lbl = np.ones((H, W), np.uint8)
    lbl[1:3, 2:5] = 0
    scipy.io.savemat(str(root / "CZ_hsdb" / "img1.mat"), {"ref": ref, "lbl": lbl})
    calib = np.linspace(0.5, 2.0, 31)
    (root / "calib.txt").write_text("\n".join(repr(float(c)) for c in calib) + "\n")
    return root / "CZ_hsdb" / "img1.mat", ref, lbl, calib


def test_lbl_polarity_is_an_option(tmp_path):
    f, _, lbl, _ = _scene(tmp_path)
    default = load_source(tmp_path, "harvard")[0].mask((H, W))
    np.testing.assert_array_equal(default != 0, lbl == 0)
    flipped = load_source(tmp_path, "harvard",
                          options=SourceOptions(harvard_lbl="nonzero-excluded"))[0].mask((H, W))
    np.testing.assert_array_equal(flipped != 0, lbl != 0)
    ignored = load_source(tmp_path, "harvard",
                          options=SourceOptions(harvard_lbl="ignore"))[0].mask((H, W))
    assert not ignored.any()
    with pytest.raises(InputError, match="harvard_lbl must be one of"):
        SourceOptions(harvard_lbl="ones")


def test_calib_is_not_applied_by_default_and_either_direction_on_request(tmp_path):
    f, ref, _, calib = _scene(tmp_path)
    opts_all = dict(bands="all")
    data, wl, info = read_source_cube("harvard", f, SourceOptions(**opts_all))
    np.testing.assert_array_equal(data, ref.astype(np.float32))
    assert info["calib"] == "not applied" and info["options"]["harvard_calib"] == "none"
    data, _, info = read_source_cube("harvard", f, SourceOptions(harvard_calib="divide",
                                                                 **opts_all))
    np.testing.assert_allclose(data[0, 0], (np.arange(1.0, 32.0) / calib).astype(np.float32))
    assert info["calib_file"] == str((tmp_path / "calib.txt").resolve())
    data, wl, _ = read_source_cube("harvard", f, SourceOptions(harvard_calib="multiply"))
    # applied per stored band before the default selection (420–700 nm, 29 bands)
    np.testing.assert_allclose(data[0, 0], (np.arange(1.0, 30.0) * calib[:29]).astype(np.float32))
    np.testing.assert_array_equal(wl, WL[:29])


def test_calib_errors_name_the_file(tmp_path):
    f, *_ = _scene(tmp_path)
    (tmp_path / "calib.txt").write_text(" ".join(["1.0"] * 30))
    with pytest.raises(FormatError, match="30 numbers") as e:
        read_source_cube("harvard", f, SourceOptions(harvard_calib="divide"))
    assert "calib.txt" in str(e.value)
    (tmp_path / "calib.txt").unlink()
    with pytest.raises(InputError, match="calib.txt") as e:
        read_source_cube("harvard", f, SourceOptions(harvard_calib="divide"))
    assert "img1.mat" in str(e.value)


def test_cli_options_reach_the_reader(tmp_path):
    _scene(tmp_path)
    p = argparse.ArgumentParser()
    add_source_arguments(p)
    args = p.parse_args(["--harvard-lbl", "ignore", "--harvard-calib", "multiply"])
    apply_source_arguments(args, tmp_path)
    fmt, opts = remembered(tmp_path)
    assert fmt == "harvard" and opts.harvard_lbl == "ignore" and opts.harvard_calib == "multiply"
    ps = load_source(tmp_path)
    assert ps.manifest["options"]["harvard_calib"] == "multiply"
    assert not ps[0].mask((H, W)).any()
