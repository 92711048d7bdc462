"""`mehs info`: summaries of ENVI / Specim IQ / EXR, and clean errors on bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io import write_envi, write_specim_folder
from mehs.io.specim import SpecimCapture

WL = np.round(np.linspace(397.32, 1003.58, 204), 2)


def _raw_cube(lines=8, samples=6, seed=0, saturate=0):
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 4000, (lines, samples, 204)).astype(np.uint16)
    data.reshape(-1)[:saturate] = 4095
    return SpectralCube(data, WL, integration_time_ms=12.5, acquisition_date="2018-11-22",
                        default_bands=(69, 52, 18), binning=(1, 1))


def _info_json(capsys, *argv) -> dict:
    assert main(["info", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_envi_summary(tmp_path, capsys):
    cube = _raw_cube(saturate=204 * 3)  # first three pixels saturated in every band
    hp = write_envi(tmp_path / "c.hdr", cube, interleave="bsq")
    info = _info_json(capsys, str(hp))
    assert info["format"] == "ENVI"
    assert info["shape"] == [8, 6, 204] and info["dtype"] == "uint16"
    assert info["interleave"] == "bsq" and info["byte_order"].startswith("0")
    assert info["wavelengths"]["count"] == 204
    assert info["wavelengths"]["min_nm"] == 397.32 and info["wavelengths"]["max_nm"] == 1003.58
    assert info["integration_time_ms"] == 12.5 and info["acquisition_date"] == "2018-11-22"
    assert [d["band"] for d in info["default_bands"]] == [70, 53, 19]
    assert info["default_bands"][0]["nm"] == pytest.approx(WL[69])
    v = info["values"]
    assert v["min"] == int(cube.data.min()) and v["max"] == 4095
    assert v["saturation_level"] == 4095 and v["sampled"] is False
    assert v["saturated_fraction"] == pytest.approx((cube.data >= 4095).mean())
    assert v["saturated_pixel_fraction"] == pytest.approx(3 / 48)


def test_envi_text_and_sampling(tmp_path, capsys):
    hp = write_envi(tmp_path / "c.hdr", _raw_cube(lines=50))
    assert main(["info", str(hp), "--lines", "5"]) == 0
    out = capsys.readouterr().out
    for needle in ("ENVI", "50 × 6 × 204", "uint16, interleave bil", "204 bands, 397.32–1003.58 nm",
                   "12.5 ms", "70 (", "sampled 5 of 50 lines", "≥ 4095 (12-bit"):
        assert needle in out, needle
    # the data file also works as PATH
    info = _info_json(capsys, str(tmp_path / "c.raw"), "--lines", "5")
    assert info["values"]["lines_read"] == 5 and info["values"]["sampled"] is True


def test_float_envi_has_no_saturation_but_counts_nan(tmp_path, capsys):
    data = np.ones((3, 2, 4), np.float32)
    data[0, 0, 0] = np.nan
    hp = write_envi(tmp_path / "f.hdr", SpectralCube(data, [400, 500, 600, 700]),
                    data_ext=".dat")
    v = _info_json(capsys, str(hp))["values"]
    assert v["non_finite_values"] == 1 and "saturated_fraction" not in v
    assert v["min"] == 1.0 and v["max"] == 1.0


def test_specim_folder_summary(tmp_path, capsys):
    raw = _raw_cube()
    dark = SpectralCube(np.full((1, 6, 204), 70, np.uint16), WL, integration_time_ms=12.5)
    out = write_specim_folder(tmp_path / "A1", SpecimCapture("A1", None, raw, darkref=dark,
                                                             metadata={"k": "v"}))
    info = _info_json(capsys, str(out))
    assert info["capture_id"] == "A1" and info["manifest"] is True
    assert info["references"]["darkref"]["shape"] == [1, 6, 204]
    assert info["references"]["darkref"]["max"] == 70
    assert info["references"]["whiteref"] is None and info["missing"] == ["whiteref"]
    assert info["raw"]["shape"] == [8, 6, 204]
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Specim IQ capture 'A1'" in text and "whiteref      missing" in text


def test_exr_summary(tmp_path, capsys):
    exr = pytest.importorskip("mehs.io.exr")
    cube = SpectralCube(np.linspace(0, 2, 4 * 5 * 31, dtype=np.float32).reshape(4, 5, 31),
                        np.arange(400, 701, 10))
    p = exr.write_exr_spectral(tmp_path / "s.exr", cube)
    info = _info_json(capsys, str(p))
    assert info["format"] == "OpenEXR" and info["shape"] == [4, 5, 31]
    assert info["wavelengths"] == {"count": 31, "min_nm": 400.0, "max_nm": 700.0}
    assert info["values"]["max"] == pytest.approx(2.0)


# ---------------------------------------------------------------------- bad input


def _envi_pair(folder: Path, *, header_edit=None, data_bytes=None) -> Path:
    hp = write_envi(folder / "in.hdr", _raw_cube(lines=2, samples=2))
    if header_edit:
        hp.write_text(header_edit(hp.read_text()))
    if data_bytes is not None:
        (folder / "in.raw").write_bytes((folder / "in.raw").read_bytes()[:data_bytes])
    return hp


def _drop_line(key):
    return lambda t: "\n".join(ln for ln in t.splitlines() if not ln.startswith(key)) + "\n"


def _replace_wavelengths(values):
    def edit(t):
        lines = [ln for ln in t.splitlines() if not ln.startswith("wavelength =")]
        return "\n".join(lines) + f"\nwavelength = {{{', '.join(values)}}}\n"
    return edit


WL_TEXT = [repr(float(w)) for w in WL]

CLI_BAD = {
    "truncated": (dict(data_bytes=100), "in.raw: data file is truncated: expected"),
    "missing_key": (dict(header_edit=_drop_line("bands")),
                    "in.hdr: mandatory header key 'bands' is missing"),
    "unknown_dtype": (dict(header_edit=lambda t: t.replace("data type = 12", "data type = 8")),
                      "in.hdr: unknown ENVI data type '8'"),
    "band_count": (dict(header_edit=_replace_wavelengths(WL_TEXT[:-1])),
                   "in.hdr: 'wavelength' has 203 values for 204 bands"),
    "non_numeric": (dict(header_edit=_replace_wavelengths(WL_TEXT[:-1] + ["n/a"])),
                    "in.hdr: 'wavelength' value 'n/a' (band 204) is not a number"),
    "duplicate": (dict(header_edit=_replace_wavelengths(WL_TEXT[:-1] + [WL_TEXT[0]])),
                  "in.hdr: 'wavelength': duplicate wavelengths [397.32]"),
}


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.stat().st_size for p in folder.rglob("*")}


def _assert_clean_error(capsys, argv, needle):
    assert main(argv) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.startswith("mehs: error: ") and needle in cap.err, cap.err
    assert "Traceback" not in cap.err


@pytest.mark.parametrize("case", sorted(CLI_BAD))
def test_cli_bad_envi(tmp_path, capsys, case):
    kwargs, needle = CLI_BAD[case]
    hp = _envi_pair(tmp_path, **kwargs)
    before = _snapshot(tmp_path)
    _assert_clean_error(capsys, ["info", str(hp)], needle)
    assert _snapshot(tmp_path) == before


def _capture_folder(tmp_path) -> Path:
    raw = _raw_cube(lines=2, samples=2)
    dark = SpectralCube(np.full((1, 2, 204), 70, np.uint16), WL)
    return write_specim_folder(tmp_path / "444", SpecimCapture("444", None, raw, darkref=dark))


def test_cli_specim_missing_raw(tmp_path, capsys):
    out = _capture_folder(tmp_path)
    for ext in ("hdr", "raw"):
        (out / "capture" / f"444.{ext}").unlink()
    before = _snapshot(tmp_path)
    _assert_clean_error(capsys, ["info", str(out)], "444: raw cube missing: capture/444.hdr")
    assert _snapshot(tmp_path) == before


def test_cli_specim_missing_dark(tmp_path, capsys):
    out = _capture_folder(tmp_path)
    for ext in ("hdr", "raw"):
        (out / "capture" / f"DARKREF_444.{ext}").unlink()
    before = _snapshot(tmp_path)
    _assert_clean_error(capsys, ["info", str(out)],
                        "444: dark reference missing: capture/DARKREF_444.hdr not found")
    assert _snapshot(tmp_path) == before
    # on request info describes what is there and lists what is missing
    info = _info_json(capsys, str(out), "--allow-missing-dark")
    assert info["references"]["darkref"] is None and "darkref" in info["missing"]


def test_cli_path_does_not_exist(tmp_path, capsys):
    _assert_clean_error(capsys, ["info", str(tmp_path / "ghost.hdr")],
                        "ghost.hdr: file or folder does not exist")
    assert list(tmp_path.iterdir()) == []


def test_cli_folder_that_is_not_a_capture(tmp_path, capsys):
    _assert_clean_error(capsys, ["info", str(tmp_path)], "folder is not a Specim IQ capture")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_cli_exr_with_nan_or_inf(tmp_path, capsys, bad):
    exr = pytest.importorskip("mehs.io.exr")
    img = np.ones((3, 4, 3), np.float32)
    img[1, 2, 0] = bad
    p = tmp_path / "bad.exr"
    # write the broken file with OpenEXR directly: mehs's writer may refuse NaN.
    # (The bindings ignore strides: planes must be contiguous.)
    import OpenEXR

    planes = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGB")}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 planes).write(str(p))
    before = _snapshot(tmp_path)
    _assert_clean_error(capsys, ["info", str(p)], "bad.exr: 1 NaN/Inf pixel values")
    assert _snapshot(tmp_path) == before
    del exr


def test_cli_subprocess_error_has_no_traceback(tmp_path):
    hp = _envi_pair(tmp_path, data_bytes=10)
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    res = subprocess.run([sys.executable, "-m", "mehs", "info", str(hp)],
                         capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 2
    assert res.stdout == ""
    assert res.stderr.startswith(f"mehs: error: {tmp_path / 'in.raw'}: data file is truncated")
    assert "Traceback" not in res.stderr
    ok = subprocess.run([sys.executable, "-m", "mehs", "info", "--json",
                         str(write_envi(tmp_path / "ok.hdr", _raw_cube(lines=2, samples=2)))],
                        capture_output=True, text=True, env=env, timeout=60)
    assert ok.returncode == 0 and json.loads(ok.stdout)["shape"] == [2, 2, 204]
