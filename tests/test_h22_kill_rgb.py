"""`mehs rgb` killed while it writes its images (the fix is in mehs/cli/rgb.py).

``rgb.json`` is written last; a run killed before it used to leave images that the same
command then refused to replace ("output exists"), and a ``--force`` run killed half-way
left the earlier ``rgb.json`` describing a mix of two runs' images.
"""

import json

import numpy as np
import pytest

import mehs.preview as preview
from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io.envi import write_envi


class Killed(BaseException):
    """Stands for SIGKILL."""


@pytest.fixture()
def cube_hdr(tmp_path):
    rng = np.random.default_rng(0)
    cube = SpectralCube(rng.uniform(0.1, 1.0, (4, 5, 7)).astype(np.float32),
                        np.linspace(400, 700, 7), units="relative radiance")
    return write_envi(tmp_path / "in" / "c.hdr", cube, dtype="float32", data_ext=".dat")


def _die_at_preview(monkeypatch):
    real = preview.write_png

    def dying(path, *a, **kw):
        if str(path).endswith("preview.png"):
            raise Killed
        return real(path, *a, **kw)

    monkeypatch.setattr(preview, "write_png", dying)


def test_a_killed_rgb_is_finished_by_the_same_command(cube_hdr, tmp_path, monkeypatch):
    ref, out = tmp_path / "ref", tmp_path / "out"
    assert main(["rgb", str(cube_hdr), "--out", str(ref)]) == 0
    _die_at_preview(monkeypatch)
    with pytest.raises(Killed):
        main(["rgb", str(cube_hdr), "--out", str(out)])
    monkeypatch.undo()
    assert (out / "hdr_rgb.exr").exists() and not (out / "rgb.json").exists()
    assert main(["rgb", str(cube_hdr), "--out", str(out)]) == 0
    for n in ("hdr_rgb.exr", "ldr_rgb.png", "preview.png"):
        assert (out / n).read_bytes() == (ref / n).read_bytes()


def test_a_forced_rgb_killed_half_way_leaves_no_earlier_rgb_json(cube_hdr, tmp_path, monkeypatch):
    out = tmp_path / "out"
    assert main(["rgb", str(cube_hdr), "--out", str(out), "--ldr-exposure", "0.5"]) == 0
    assert json.loads((out / "rgb.json").read_text())["ldr_rgb"]["exposure"] == 0.5
    _die_at_preview(monkeypatch)
    with pytest.raises(Killed):
        main(["rgb", str(cube_hdr), "--out", str(out), "--ldr-exposure", "2", "--force"])
    # the new LDR image is in place; no rgb.json may claim exposure 0.5 for it
    assert not (out / "rgb.json").exists()
