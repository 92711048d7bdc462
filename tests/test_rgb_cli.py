"""`mehs resample`, `mehs rgb` and `mehs export` end to end on small ENVI cubes."""

import json

import numpy as np
import pytest

from mehs.cli import main
from mehs.cube import SpectralCube
from mehs.io.envi import read_envi, write_envi
from mehs.io.exr import read_exr, read_exr_spectral
from mehs.preview import read_png
from mehs.rgb import WAVELENGTHS_31, hdr_rgb, ldr_rgb
from mehs.synthesis.resample import resample_cube

RNG = np.random.default_rng(7)
SPECIM_WL = np.linspace(397.32, 1003.58, 204)


@pytest.fixture
def raw_hdr(tmp_path):
    data = (RNG.random((10, 12, 204)) * 4000).astype(np.uint16)
    cube = SpectralCube(data, SPECIM_WL, integration_time_ms=20.0)
    return write_envi(tmp_path / "in" / "cube.hdr", cube)


@pytest.fixture
def hs31_hdr(tmp_path):
    data = (RNG.random((9, 11, 31)) * 50).astype(np.float32)
    data[0, 0] *= 1000  # a bright source
    return write_envi(tmp_path / "hs" / "hs.hdr", SpectralCube(data, WAVELENGTHS_31,
                                                               units="relative radiance"),
                      data_ext=".dat")


def test_resample_cli_envi_and_exr(tmp_path, raw_hdr, capsys):
    out = tmp_path / "out" / "hs.hdr"
    assert main(["resample", str(raw_hdr), str(out)]) == 0
    assert "31 float32" in capsys.readouterr().out.replace("×", " ")
    got = read_envi(out)
    want = resample_cube(read_envi(raw_hdr))
    assert got.data.dtype == np.float32 and got.shape == (10, 12, 31)
    np.testing.assert_array_equal(np.asarray(got.data), want.data)
    np.testing.assert_array_equal(got.wavelengths, WAVELENGTHS_31)
    assert (tmp_path / "out" / "hs.dat").is_file()

    exr = tmp_path / "out" / "hs5.exr"
    assert main(["resample", str(raw_hdr), str(exr), "--bands", "450:650:50",
                 "--method", "box", "--fwhm", "20"]) == 0
    back = read_exr_spectral(exr)
    np.testing.assert_array_equal(back.wavelengths, [450, 500, 550, 600, 650])
    np.testing.assert_allclose(back.data, resample_cube(read_envi(raw_hdr), back.wavelengths,
                                                        method="box", fwhm=20).data)


def test_resample_cli_errors(tmp_path, raw_hdr, capsys):
    out = tmp_path / "o.hdr"
    assert main(["resample", str(raw_hdr), str(out), "--bands", "300:700:10"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mehs: error:") and "300 nm" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["resample", str(raw_hdr), str(raw_hdr)]) == 2
    assert "overwrite the input" in capsys.readouterr().err
    assert main(["resample", str(raw_hdr), str(tmp_path / "o.txt")]) == 2
    assert main(["resample", str(tmp_path / "missing.hdr"), str(out)]) == 2
    assert "missing.hdr" in capsys.readouterr().err
    out.write_text("x")
    assert main(["resample", str(raw_hdr), str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["resample", str(raw_hdr), str(out), "--force"]) == 0


def test_rgb_cli_writes_the_pair(tmp_path, hs31_hdr, capsys):
    out = tmp_path / "rgb"
    assert main(["rgb", str(hs31_hdr), "--out", str(out)]) == 0
    cube = read_envi(hs31_hdr)
    want = hdr_rgb(np.asarray(cube.data), WAVELENGTHS_31)
    hdr = read_exr(out / "hdr_rgb.exr")
    assert hdr.channels == ["R", "G", "B"] and hdr.data.max() > 1000
    np.testing.assert_allclose(hdr.data, want, rtol=2 ** -10)
    ldr = read_png(out / "ldr_rgb.png")
    want_ldr, exposure = ldr_rgb(want)
    np.testing.assert_array_equal(ldr, want_ldr)
    meta = json.loads((out / "rgb.json").read_text())
    assert meta["ldr_rgb"]["exposure"] == pytest.approx(exposure)
    assert meta["resampled_to_31_bands"] is False
    assert read_png(out / "preview.png").shape == (9, 11, 3)

    assert main(["rgb", str(hs31_hdr), "--out", str(out), "--ldr-exposure", "0.5",
                 "--force"]) == 0
    np.testing.assert_array_equal(read_png(out / "ldr_rgb.png"), ldr_rgb(want, exposure=0.5)[0])


def test_rgb_cli_resamples_a_raw_cube(tmp_path, raw_hdr):
    out = tmp_path / "rgb204"
    assert main(["rgb", str(raw_hdr), "--out", str(out)]) == 0
    assert json.loads((out / "rgb.json").read_text())["resampled_to_31_bands"] is True
    want = hdr_rgb(resample_cube(read_envi(raw_hdr)))
    np.testing.assert_allclose(read_exr(out / "hdr_rgb.exr").data, want, rtol=2 ** -10)


def test_export_cli(tmp_path, hs31_hdr, capsys):
    out = tmp_path / "exp"
    assert main(["export", str(hs31_hdr), "--out", str(out)]) == 0
    cube = read_envi(hs31_hdr)
    assert len(list(out.glob("band_*.exr"))) == 31
    np.testing.assert_array_equal(read_exr(out / "band_030.exr").data[:, :, 0],
                                  np.asarray(cube.data[:, :, 30]))
    np.testing.assert_array_equal(read_exr_spectral(out / "band.exr").data,
                                  np.asarray(cube.data))
    out2 = tmp_path / "exp2"
    assert main(["export", str(hs31_hdr), "--out", str(out2), "--format", "spectral",
                 "--prefix", "env"]) == 0
    assert sorted(p.name for p in out2.iterdir()) == ["env.exr"]
    assert main(["export", str(hs31_hdr), "--out", str(out2), "--prefix", "../x"]) == 2
    assert "prefix" in capsys.readouterr().err
