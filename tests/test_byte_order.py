"""A cube whose header states the wrong byte order is named, not used (issue 17, defect 8)."""

import shutil
import warnings

import numpy as np
import pytest

from mehs.cli import main
from mehs.errors import FormatError
from mehs.io.envi import read_envi
from mehs.io.plausibility import ByteOrderWarning, byte_order_suspicion


def _header(path, shape, dtype_code, byte_order, wl):
    lines, samples, bands = shape
    path.write_text("ENVI\n"
                    f"samples = {samples}\nlines = {lines}\nbands = {bands}\n"
                    f"header offset = 0\nfile type = ENVI Standard\ndata type = {dtype_code}\n"
                    f"interleave = bsq\nbyte order = {byte_order}\n"
                    f"wavelength = {{{', '.join(f'{w:.2f}' for w in wl)}}}\n")


def _smooth_12bit(lines=16, samples=20, bands=60, seed=0):
    """Smooth spectra times a random albedo, Poisson-like noise, 12-bit range."""
    rng = np.random.default_rng(seed)
    wl = np.linspace(400, 1000, bands)
    spec = np.exp(-((wl - 620) / 160) ** 2)
    albedo = rng.uniform(0.1, 1.0, (lines, samples, 1))
    x = albedo * spec * 3900 + rng.normal(0, 8, (lines, samples, bands))
    return np.clip(np.rint(x), 0, 4095).astype(np.uint16), wl


def _write_bsq(tmp_path, name, cube, file_dtype, dtype_code, byte_order, wl):
    cube.transpose(2, 0, 1).astype(file_dtype).tofile(tmp_path / f"{name}.img")
    _header(tmp_path / f"{name}.hdr", cube.shape, dtype_code, byte_order, wl)
    return tmp_path / f"{name}.hdr"


@pytest.mark.parametrize("seed", [0, 1])
def test_big_endian_data_labelled_little_endian_is_named(tmp_path, seed, capsys):
    cube, wl = _smooth_12bit(seed=seed)
    wrong = _write_bsq(tmp_path, "wrong", cube, ">u2", 12, 0, wl)
    with pytest.warns(ByteOrderWarning, match="byte order = 0' is probably wrong"):
        read_envi(wrong)
    assert main(["info", str(wrong)]) == 0
    assert "WARNING" in capsys.readouterr().out
    # the same bytes correctly labelled: no warning, and the values come back
    right = _write_bsq(tmp_path, "right", cube, ">u2", 12, 1, wl)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ByteOrderWarning)
        np.testing.assert_array_equal(read_envi(right).data, cube)


def test_mislabelled_float32_is_named(tmp_path):
    cube, wl = _smooth_12bit()
    wrong = _write_bsq(tmp_path, "f", cube.astype(np.float32) / 4095, ">f4", 4, 0, wl)
    with pytest.warns(ByteOrderWarning, match="non-finite or beyond"):
        read_envi(wrong)


@pytest.mark.parametrize("kind", ["dark", "full16", "smooth12", "int16", "float"])
def test_plausible_data_raise_no_alarm(kind):
    rng = np.random.default_rng(3)
    if kind == "dark":  # values < 256 cannot tell the byte order apart: no guess
        data = rng.integers(20, 60, (8, 30, 50)).astype(np.uint16)
    elif kind == "full16":  # a 16-bit sensor's noise-like data: rough either way
        data = rng.integers(0, 65536, (8, 30, 50)).astype(np.uint16)
    elif kind == "smooth12":
        data = _smooth_12bit()[0]
    elif kind == "int16":  # reflectance ×10000 with negative values
        data = (_smooth_12bit()[0].astype(np.int16) * 2 - 3000)
    else:
        data = _smooth_12bit()[0].astype(np.float32) * 1e-3
    assert byte_order_suspicion(data) is None


def test_fuse_refuses_a_mislabelled_exposure(tmp_path, capsys):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    sim = simulate_bracket(make_scene("window", 24, 24, seed=1), SensorModel(seed=3),
                           (0.4, 3.2, 25.6), seed=1)
    scene = write_simulated_scene(sim, tmp_path / "s", scene_id="s")
    assert main(["fuse", str(scene), "--out", str(tmp_path / "ok"), "--response", "linear"]) == 0
    bad = tmp_path / "bad"
    shutil.copytree(scene, bad)
    raw = next((bad / "exposures").glob("2_*/capture/2_*.raw"))
    raw.write_bytes(np.fromfile(raw, "<u2").astype(">u2").tobytes())  # big-endian bytes
    capsys.readouterr()
    out = tmp_path / "fused"
    assert main(["fuse", str(bad), "--out", str(out), "--response", "linear",
                 "--verify", "none"]) == 2
    err = capsys.readouterr().err
    assert raw.with_suffix(".hdr").name in err and "byte order = 0" in err
    assert not (out / "radiance.hdr").exists()
    with pytest.raises(FormatError, match="byte-swapped"):
        from mehs.synthesis.bracket import load_bracket

        load_bracket(bad, verify="none")
