"""The stored power-of-two scale of a dataset scene (and of `mehs rgb`) against outside truth:
colour-science's XYZ of the input spectra, half float's precision, SPy reading ``hs.hdr``."""

import json

import numpy as np
import pytest

from _checks import colour_srgb, ohta_chart
from mehs.cube import SpectralCube
from mehs.dataset.build import build_from_hs
from mehs.dataset.cube_figures import half_float_scale
from mehs.dataset.manifest import read_manifest
from mehs.io.envi import write_envi
from mehs.io.exr import HALF_MAX, read_exr
from mehs.rgb import WAVELENGTHS_31

UNIT = "W sr-1 m-2 nm-1"
#: half float's smallest normal 2^-14, six stops up: where a scene's low end is stored
HALF_LOW_END = 2.0 ** -8


def _build(tmp_path, cube):
    write_envi(tmp_path / "in" / "cc.hdr", SpectralCube(cube, WAVELENGTHS_31, units=UNIT))
    build_from_hs([tmp_path / "in"], tmp_path / "ds", workers=1, progress=False)
    return read_manifest(tmp_path / "ds")["scenes"][0]


@pytest.mark.parametrize("level", [1e-3, 1e-5])
def test_dim_scene_keeps_half_float_precision_in_the_rgb_exr(tmp_path, level):
    """A chart at 10⁻⁵ (absolute radiance of a dim scene) lay below half's smallest normal:
    the EXR was off by up to 32 % (0.36 % at 10⁻³); lifted by 2^k it keeps 11 bits."""
    cube = ohta_chart(level)
    s = _build(tmp_path, cube)
    scale = s["quality"]["radiance_scale"]
    exr = read_exr(tmp_path / "ds" / s["files"]["hdr_rgb"])
    assert exr.header["mehsRadianceScale"] == scale > 1
    got = exr.data[:, :, :3].astype(np.float64) / scale
    ref = colour_srgb(cube)
    ok = ref > 1e-6 * ref.max()          # channels not decided by rounding in the matrix
    rel = np.abs(got - ref)[ok] / ref[ok]
    assert rel.max() < 2 ** -10          # half rounding (2^-11) and float32 sums
    # the cube carries the same exact factor: HS and RGB stay paired
    from mehs.io.envi import read_envi

    hs = read_envi(tmp_path / "ds" / s["files"]["hs"])
    np.testing.assert_array_equal(np.asarray(hs.data) / np.float32(scale), cube)
    assert float(hs.metadata["mehs radiance scale"]) == scale


def test_a_scene_in_range_keeps_its_values_and_header(tmp_path):
    s = _build(tmp_path, ohta_chart(1.0))
    assert s["quality"]["radiance_scale"] == 1.0
    text = (tmp_path / "ds" / s["files"]["hs"]).read_text()
    assert "data gain values" not in text


@pytest.mark.parametrize("level", [1e-5, 3e4])
def test_spy_reads_the_radiance_through_the_envi_gain(tmp_path, level):
    """SPy knows nothing of ``mehs radiance scale``: the header states the factor the ENVI
    way (``data gain values``; value · gain + offset is in ``data units``)."""
    import spectral

    cube = ohta_chart(level)
    s = _build(tmp_path, cube)
    scale = s["quality"]["radiance_scale"]
    assert scale != 1
    img = spectral.envi.open(str(tmp_path / "ds" / s["files"]["hs"]))
    gain = np.asarray(img.metadata["data gain values"], dtype=np.float64)
    offset = np.asarray(img.metadata["data offset values"], dtype=np.float64)
    assert gain.shape == offset.shape == (31,)
    assert np.all(gain == 1 / scale) and np.all(offset == 0)
    assert img.metadata["data units"] == UNIT
    np.testing.assert_array_equal(np.asarray(img.open_memmap()) * gain + offset, cube)


def test_half_float_scale_rule():
    # bright: the smallest 2^-k that fits the peak (as before)
    assert half_float_scale(2e5) == 0.25 and half_float_scale(HALF_MAX) == 1.0
    assert half_float_scale(2e5, low=1e-9) == 0.25          # the peak wins over the low end
    # in range: untouched
    assert half_float_scale(100.0, low=HALF_LOW_END) == 1.0
    assert half_float_scale(100.0) == 1.0
    # dim: the low end lifted to at least 2^-8, as far as the peak allows
    s = half_float_scale(1e-3, low=1e-7)
    assert s == 2.0 ** 16 and 1e-7 * s >= HALF_LOW_END > 1e-7 * s / 2
    s = half_float_scale(30.0, low=1e-9)
    assert 30.0 * s <= HALF_MAX < 60.0 * s
    for bad in (0.0, float("nan"), float("inf")):
        assert half_float_scale(bad, low=1e-9) == 1.0


def test_rgb_cli_keeps_precision_and_carries_a_dataset_cubes_scale(tmp_path):
    """`mehs rgb` of a dim cube stored it with half's precision lost, and of a dataset's
    ``hs.hdr`` wrote its 2^-k values into the EXR without saying so."""
    from mehs.cli import main

    cube = ohta_chart(1e-5)
    s = _build(tmp_path, cube)
    ds_scale = s["quality"]["radiance_scale"]
    ref = colour_srgb(cube)
    ok = ref > 1e-6 * ref.max()
    for src in (tmp_path / "in" / "cc.hdr", tmp_path / "ds" / s["files"]["hs"]):
        out = tmp_path / f"rgb_{src.parent.name}"
        assert main(["rgb", str(src), "--out", str(out)]) == 0
        exr = read_exr(out / "hdr_rgb.exr")
        meta = json.loads((out / "rgb.json").read_text())
        total = exr.header["mehsRadianceScale"]
        assert meta["hdr_rgb"]["radiance_scale"] == total == ds_scale
        got = exr.data[:, :, :3].astype(np.float64) / total
        assert (np.abs(got - ref)[ok] / ref[ok]).max() < 2 ** -10
        # the recorded exposure takes the stored values to the PNG
        from mehs.rgb import ldr_rgb
        png = ldr_rgb(exr.data[:, :, :3].astype(np.float32),
                      exposure=meta["ldr_rgb"]["exposure"])[0]
        from mehs.preview import read_png
        assert np.abs(png.astype(int) - read_png(out / "ldr_rgb.png")).max() <= 1


def test_export_half_warns_when_values_fall_below_half_normal(tmp_path, capsys):
    """`mehs export --half` of a cube in dim absolute radiance lost precision silently
    (half keeps 11 bits only from 2^-14 up); a dataset cube (lifted) exports quietly."""
    from mehs.cli import main

    dim = write_envi(tmp_path / "dim" / "c.hdr",
                     SpectralCube(ohta_chart(1e-5), WAVELENGTHS_31, units=UNIT))
    assert main(["export", str(dim), "--out", str(tmp_path / "e1"), "--half"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "smallest normal" in err and str(dim) in err
    s = _build(tmp_path, ohta_chart(1e-5))
    assert main(["export", str(tmp_path / "ds" / s["files"]["hs"]), "--out",
                 str(tmp_path / "e2"), "--half"]) == 0
    assert "warning" not in capsys.readouterr().err
    # the exported values carry the scene's scale, stated in every file
    exr = read_exr(tmp_path / "e2" / "band_015.exr")
    assert exr.header["mehsRadianceScale"] == s["quality"]["radiance_scale"]
    np.testing.assert_allclose(exr.data[:, :, 0] / s["quality"]["radiance_scale"],
                               ohta_chart(1e-5)[:, :, 15], rtol=2 ** -11)
