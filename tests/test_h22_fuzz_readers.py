"""Damaged and hostile input files: a clear error naming the file, never a wrong number.

Mutants of small valid inputs, made the way lab files get damaged (a line appended in a
text editor, a header saved as UTF-16, another vendor's units line, a hand-edited
scene.json, a colour PNG among band images). The valid inputs are written by
independent tools (SPy's ``envi.save_image``, h5py, OpenCV), not by mehs.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

from mehs.cli import main
from mehs.errors import FormatError, InputError
from mehs.io import load_cube

WL = np.arange(400.0, 701.0, 10.0)


def _cube(seed=0, shape=(6, 7)):
    """Smooth positive spectra over 31 bands, magnitudes 0.5 … 6e4 (a DN/ms radiance)."""
    rng = np.random.default_rng(seed)
    spec = np.exp(-((WL - 560.0) / 120.0) ** 2)
    albedo = rng.lognormal(4.0, 2.0, shape + (1,))
    return (albedo * spec + rng.uniform(0.5, 1.0, shape + (WL.size,))).astype(np.float32)


def _spy_cube(tmp_path, data=None, byteorder=0):
    import spectral.io.envi as envi

    data = _cube() if data is None else data
    hdr = tmp_path / "c.hdr"
    envi.save_image(str(hdr), data, dtype=np.float32, interleave="bil", byteorder=byteorder,
                    ext=".img", force=True,
                    metadata={"wavelength": [f"{w:g}" for w in WL], "wavelength units": "Nanometers"})
    return hdr, data


def _edit(hdr, fn, encoding="utf-8"):
    text = hdr.read_text(encoding="utf-8")
    hdr.write_bytes(fn(text).encode(encoding) if isinstance(fn(text), str) else fn(text))


def _set(text, key, value):
    import re

    return re.sub(rf"(?im)^{key}\s*=.*$", f"{key} = {value}", text, count=1)


# mutants the reader must take, with the very same numbers: (name, header text → bytes)
SAME = {
    "crlf": lambda t: t.replace("\n", "\r\n").encode(),
    "utf8_bom": lambda t: b"\xef\xbb\xbf" + t.encode(),
    "utf16_bom": lambda t: t.encode("utf-16"),
    "utf16le_no_bom": lambda t: t.encode("utf-16-le"),
    "same_key_twice": lambda t: (t + "samples = 7\n").encode(),
}


@pytest.mark.parametrize("name", sorted(SAME))
def test_harmless_header_variants_read_the_same_numbers(tmp_path, name):
    hdr, data = _spy_cube(tmp_path)
    hdr.write_bytes(SAME[name](hdr.read_text()))
    cube = load_cube(hdr)
    np.testing.assert_array_equal(cube.data, data)
    np.testing.assert_allclose(cube.wavelengths, WL)


# mutants that must be refused: (header text → text, words the message must hold)
REFUSED = {
    # appended in an editor: which shape is meant cannot be told (the size matches both)
    "lines_samples_twice": (lambda t: t + "samples = 14\nlines = 3\n", "'samples' is given 2 times"),
    "wavelength_twice": (lambda t: t + "wavelength = {" + ", ".join(f"{w + 5:g}" for w in WL)
                         + "}\n", "'wavelength' is given 2 times"),
    "nm_labelled_um": (lambda t: _set(t, "wavelength units", "Micrometers"), "µm"),
    "um_labelled_nm": (lambda t: _set(t, "wavelength", "{" + ", ".join(
        f"{w / 1000:g}" for w in WL) + "}"), "micrometres?"),
    "empty": (lambda t: "", "empty"),
    "samples_overflow": (lambda t: _set(t, "samples", "99999999"), "truncated"),
    "header_offset_past_end": (lambda t: _set(t, "header offset", "99999999"), "truncated"),
    "wavelength_short": (lambda t: _set(t, "wavelength", "{400, 410}"), "2 values for 31"),
    "lines_negative": (lambda t: _set(t, "lines", "-6"), "'lines' = -6"),
    "samples_text": (lambda t: _set(t, "samples", "seven"), "not an integer"),
    "truncated_mid_list": (lambda t: t[:t.index("wavelength = {") + 30], "cannot be parsed"),
}


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_damaged_headers_are_named_errors(tmp_path, name):
    hdr, _ = _spy_cube(tmp_path)
    fn, words = REFUSED[name]
    hdr.write_text(fn(hdr.read_text()))
    with pytest.raises(FormatError, match=words.replace("?", r"\?")) as err:
        load_cube(hdr)
    assert err.value.path and err.value.path.endswith(("c.hdr", "c.img"))


def test_cli_names_a_conflicting_header_without_traceback(tmp_path, capsys):
    hdr, _ = _spy_cube(tmp_path)
    hdr.write_text(hdr.read_text() + "lines = 3\nsamples = 14\n")
    assert main(["info", str(hdr)]) == 2
    assert main(["resample", str(hdr), str(tmp_path / "o.hdr")]) == 2
    err = capsys.readouterr().err
    assert "c.hdr: header key 'lines' is given 2 times" in err and "Traceback" not in err
    assert not (tmp_path / "o.hdr").exists()


def test_empty_data_units_keep_the_default(tmp_path):
    hdr, _ = _spy_cube(tmp_path)
    hdr.write_text(hdr.read_text() + "data units = \n")
    assert load_cube(hdr).units == "unknown"


@pytest.mark.parametrize("seed", [0, 1])
def test_float_cube_with_the_wrong_byte_order_is_named(tmp_path, seed):
    """SPy writes the cube big-endian; the header is edited to say little-endian.

    Swapped, ~48 % of such floats fall beyond 1e±20 (these two cubes: 47.6 %, 49.0 %):
    the old test (more than half) missed them all."""
    from mehs.io.plausibility import ByteOrderWarning

    hdr, data = _spy_cube(tmp_path, data=_cube(seed, (16, 16)), byteorder=1)
    with pytest.warns(ByteOrderWarning, match="byte order = 0' is probably wrong"):
        hdr.write_text(_set(hdr.read_text(), "byte order", "0"))
        load_cube(hdr)
    hdr.write_text(_set(hdr.read_text(), "byte order", "1"))   # the truth: no alarm
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", ByteOrderWarning)
        np.testing.assert_array_equal(load_cube(hdr).data, data)


def test_exr_spectral_imports_first_in_a_fresh_process():
    r = subprocess.run([sys.executable, "-c", "import mehs.io.exr_spectral"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-500:]


# --------------------------------------------------------------------- scene.json
@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("fz")
    sim = simulate_bracket(make_scene("window", 12, 12, seed=1), SensorModel(seed=3),
                           (0.4, 3.2, 25.6), seed=1)
    return write_simulated_scene(sim, root / "s", scene_id="s")


def _scene_copy(scene, tmp_path, edit):
    import shutil

    dst = tmp_path / "s"
    shutil.copytree(scene, dst)
    sj = dst / "scene.json"
    doc = json.loads(sj.read_text())
    edit(doc)
    sj.write_text(json.dumps(doc))
    return dst


@pytest.mark.parametrize("name, edit, words", [
    ("time_differs_from_header", lambda d: d["exposures"][1].__setitem__(
        "integration_time_ms", d["exposures"][1]["integration_time_ms"] * 10), "header 'tint'"),
    ("folder_outside", lambda d: d["exposures"][0].__setitem__("folder", "../elsewhere"),
     "outside the scene folder"),
    ("folder_absolute", lambda d: d["exposures"][0].__setitem__("folder", "/tmp"),
     "outside the scene folder"),
    ("time_text", lambda d: d["exposures"][0].__setitem__("integration_time_ms", "abc"),
     "not a positive number"),
    ("files_list", lambda d: d["exposures"][0].__setitem__("files", []), "'files' must map"),
])
def test_hand_edited_scene_json_is_refused_by_fuse_and_build(scene, tmp_path, capsys, name,
                                                            edit, words):
    bad = _scene_copy(scene, tmp_path, edit)
    assert main(["fuse", str(bad), "--out", str(tmp_path / "f"), "--response", "linear"]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err
    assert not (tmp_path / "f").exists()
    if name != "time_differs_from_header":          # build reads scene.json first
        from mehs.capture.scenefolder import read_scene_json

        with pytest.raises(FormatError, match=words):
            read_scene_json(bad)


# --------------------------------------------------------------------- public SSR sets
def _arad_mat(path, cube, bands, norm=np.array([[1.0]])):
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        f["cube"] = np.ascontiguousarray(cube.transpose())      # MATLAB column-major
        f["bands"] = bands.reshape(1, -1)
        f["norm_factor"] = norm


def test_arad_norm_factor_that_is_no_number_is_named(tmp_path):
    from mehs.io.ssr_datasets import read_source_cube

    _arad_mat(tmp_path / "a.mat", _cube(), WL, norm=np.array([b"x"]))
    with pytest.raises(FormatError, match="'norm_factor' must be a number"):
        read_source_cube("arad1k", tmp_path / "a.mat")


def test_bands_listed_red_to_blue_come_back_in_ascending_order(tmp_path):
    from mehs.io.ssr_datasets import read_source_cube

    data = _cube()
    _arad_mat(tmp_path / "up.mat", data, WL)
    _arad_mat(tmp_path / "down.mat", data[:, :, ::-1], WL[::-1])
    up, wl_up, _ = read_source_cube("arad1k", tmp_path / "up.mat")
    down, wl_down, _ = read_source_cube("arad1k", tmp_path / "down.mat")
    np.testing.assert_array_equal(wl_down, WL)
    np.testing.assert_array_equal(down, up)


def test_cave_colour_png_among_band_images_is_named(tmp_path):
    import cv2

    from mehs.io.ssr_datasets import read_source_cube

    folder = tmp_path / "balloons_ms"
    folder.mkdir()
    grey = (_cube() / 7e4 * 65535).astype(np.uint16)
    for k in range(31):
        cv2.imwrite(str(folder / f"balloons_ms_{k + 1:02d}.png"), grey[:, :, k])
    read_source_cube("cave", folder)
    colour = np.dstack([grey[:, :, 4], grey[:, :, 4] // 2, grey[:, :, 4]])
    cv2.imwrite(str(folder / "balloons_ms_05.png"), colour)
    with pytest.raises(FormatError, match="colour channels that differ") as err:
        read_source_cube("cave", folder)
    assert err.value.path.endswith("balloons_ms_05.png")
    # identical channels (as a few real CAVE files are stored) are one grey plane
    cv2.imwrite(str(folder / "balloons_ms_05.png"), np.dstack([grey[:, :, 4]] * 3))
    read_source_cube("cave", folder)


def test_inputerror_family():
    assert issubclass(FormatError, InputError)
