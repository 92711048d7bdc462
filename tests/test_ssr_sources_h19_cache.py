"""Source caches follow the file, not its name: a scene rewritten in the same process is
read anew (audit h19, item 1)."""

from __future__ import annotations

import os

import cv2
import h5py
import numpy as np
import scipy.io

from mehs.ssr.sources import load_source

WL34 = np.arange(400.0, 731.0, 10.0)


def _write_kaust(path, value: float, h: int = 6) -> np.ndarray:
    c = np.full((h, 5, 34), value, dtype=np.float32)
    c[0, 0] = np.linspace(0.1, 0.9, 34)  # a spectrum that is no constant
    with h5py.File(path, "w") as f:
        f["img"] = c
        f["bands"] = WL34
    return c


def test_kaust_file_rewritten_in_place_is_read_again(tmp_path):
    root = tmp_path / "kaust"
    root.mkdir()
    f = root / "scene_01.h5"
    _write_kaust(f, 0.25)
    first, _ = load_source(root)[0].hs_array()
    assert np.allclose(first[1:, 1:], 0.25)
    old = f.stat()
    new = _write_kaust(f, 0.5)  # same size, same inode: only its times differ
    # a re-export comes later than the coarse clock tick of the first write: say so
    os.utime(f, ns=(old.st_atime_ns, old.st_mtime_ns + 10_000_000))
    assert f.stat().st_ino == old.st_ino and f.stat().st_size == old.st_size
    again, _ = load_source(root)[0].hs_array()
    np.testing.assert_array_equal(again, new[..., :31])


def test_kaust_file_replaced_by_rename_is_read_again(tmp_path):
    root = tmp_path / "kaust"
    root.mkdir()
    f = root / "scene_01.h5"
    _write_kaust(f, 0.25)
    assert np.allclose(load_source(root)[0].hs_array()[0][1:, 1:], 0.25)
    tmp = tmp_path / "new.h5"
    new = _write_kaust(tmp, 0.75)
    os.replace(tmp, f)  # how atomic exporters write: a new inode under the old name
    np.testing.assert_array_equal(load_source(root)[0].hs_array()[0], new[..., :31])
    # the RGB is rendered from the new cube too
    rgb = load_source(root)[0].hdr_rgb()
    assert rgb[3, 3].sum() > 0 and np.isfinite(rgb).all()


def test_cave_band_rewritten_is_read_again(tmp_path):
    d = tmp_path / "cave" / "balloons_ms" / "balloons_ms"
    d.mkdir(parents=True)
    for b in range(31):
        assert cv2.imwrite(str(d / f"balloons_ms_{b + 1:02d}.png"),
                           np.full((4, 4), 1000 * (b + 1), np.uint16))
    p = load_source(tmp_path / "cave")[0]
    assert p.hs_array()[0][0, 0, 16] == np.float32(17000 / 65535)
    png = d / "balloons_ms_17.png"
    tmp = tmp_path / "b17.png"
    assert cv2.imwrite(str(tmp), np.full((4, 4), 40000, np.uint16))
    os.replace(tmp, png)
    assert load_source(tmp_path / "cave")[0].hs_array()[0][0, 0, 16] == np.float32(40000 / 65535)


def test_harvard_lbl_rewritten_changes_the_mask(tmp_path):
    root = tmp_path / "harvard"
    root.mkdir()
    f = root / "img1.mat"
    ref = np.full((4, 5, 31), 0.5)
    lbl = np.ones((4, 5))
    scipy.io.savemat(f, {"ref": ref, "lbl": lbl})
    assert load_source(root, "harvard")[0].mask().sum() == 0
    lbl[0, 0] = 0
    tmp = tmp_path / "new.mat"
    scipy.io.savemat(tmp, {"ref": ref, "lbl": lbl})
    os.replace(tmp, f)
    assert np.count_nonzero(load_source(root, "harvard")[0].mask()) == 1
