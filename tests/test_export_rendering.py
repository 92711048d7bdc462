"""Exports for spectral rendering: per-wavelength EXR sequence and one spectral EXR."""

import json

import numpy as np
import OpenEXR
import pytest

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.export import export_per_wavelength, export_spectral_exr
from mehs.io.exr import read_exr, read_exr_spectral
from mehs.rgb import WAVELENGTHS_31

RNG = np.random.default_rng(31)


@pytest.fixture
def hs_cube():
    data = (RNG.random((12, 20, 31)) * 500).astype(np.float32)
    data[0, 0] = 2e5  # an HDR light source, beyond half-float range
    return SpectralCube(data, WAVELENGTHS_31, fwhm=np.full(31, 10.0), units="relative radiance")


def test_per_wavelength_files_names_and_values(tmp_path, hs_cube):
    paths = export_per_wavelength(hs_cube, tmp_path / "env")
    assert [p.name for p in paths] == [f"band_{i:03d}.exr" for i in range(31)]
    for i, p in enumerate(paths):
        img = read_exr(p)
        assert img.channels == ["Y"]
        np.testing.assert_array_equal(img.data[:, :, 0], hs_cube.data[:, :, i])
        assert img.header["wavelength"] == 400 + 10 * i
        assert img.header["bandIndex"] == i
    f = OpenEXR.File(str(paths[0]), separate_channels=True)
    assert f.channels()["Y"].pixels.dtype == np.float32
    rows = (tmp_path / "env" / "band_wavelengths.txt").read_text().splitlines()
    assert rows[0].startswith("#") and len(rows) == 32
    assert rows[1] == "0 400.0 band_000.exr" and rows[-1] == "30 700.0 band_030.exr"
    meta = json.loads((tmp_path / "env" / "band_wavelengths.json").read_text())
    assert meta["wavelengths_nm"] == WAVELENGTHS_31.tolist()
    assert meta["files"][5] == "band_005.exr" and meta["pattern"] == "band_%03d.exr"
    assert sorted(q.name for q in (tmp_path / "env").iterdir()) == sorted(
        [p.name for p in paths] + ["band_wavelengths.txt", "band_wavelengths.json"])


def test_per_wavelength_prefix_and_errors(tmp_path, hs_cube):
    paths = export_per_wavelength(hs_cube, tmp_path, prefix="sky.2024")
    assert paths[-1].name == "sky.2024_030.exr"
    with pytest.raises(InputError, match="prefix"):
        export_per_wavelength(hs_cube, tmp_path, prefix="../evil")
    with pytest.raises(InputError, match="SpectralCube"):
        export_per_wavelength(hs_cube.data, tmp_path)
    with pytest.raises(InputError, match="half-float"):
        export_per_wavelength(hs_cube, tmp_path / "h", half=True)
    # a float64 value beyond float32's range is refused before any band is written
    big = np.array(hs_cube.data, dtype=np.float64)
    big[1, 1, 5] = 1e39
    with pytest.raises(InputError, match="32-bit float range"):
        export_per_wavelength(SpectralCube(big, hs_cube.wavelengths), tmp_path / "f")
    assert not (tmp_path / "f").exists() or not any((tmp_path / "f").iterdir())


def test_spectral_exr_reads_back_with_same_wavelengths_and_data(tmp_path, hs_cube):
    p = export_spectral_exr(hs_cube, tmp_path / "env.exr")
    back = read_exr_spectral(p)
    np.testing.assert_array_equal(back.wavelengths, WAVELENGTHS_31)
    np.testing.assert_array_equal(back.data, hs_cube.data)
    np.testing.assert_array_equal(back.fwhm, hs_cube.fwhm)
    hdr = read_exr(p).header
    assert hdr["wavelengths"] == WAVELENGTHS_31.tolist()
    assert read_exr(p).channels[:2] == ["S0.400nm", "S0.410nm"]


def test_a_dataset_cubes_radiance_scale_travels_with_the_export(tmp_path, hs_cube):
    from mehs.io.envi import read_envi, write_envi

    scaled = hs_cube.with_data(hs_cube.data * np.float32(0.25),
                               metadata={"mehs radiance scale": repr(0.25)})
    write_envi(tmp_path / "hs.hdr", scaled)
    cube = read_envi(tmp_path / "hs.hdr")           # as `mehs export DATASET/.../hs.hdr` reads it
    paths = export_per_wavelength(cube, tmp_path / "env")
    assert read_exr(paths[3]).header["mehsRadianceScale"] == 0.25
    assert json.loads((tmp_path / "env" / "band_wavelengths.json").read_text())["radiance_scale"] == 0.25
    p = export_spectral_exr(cube, tmp_path / "s.exr")
    assert read_exr(p).header["mehsRadianceScale"] == 0.25
    # a cube without one says so (null), not 1
    export_per_wavelength(hs_cube, tmp_path / "plain")
    assert json.loads((tmp_path / "plain" / "band_wavelengths.json").read_text())["radiance_scale"] is None
