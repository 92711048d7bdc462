"""Spectral EXR channel names (KAIST ``w<λ>nm``, mixed schemes, repeated wavelengths) and
Fichet 2021 ``emissiveUnits`` (audit h19, items 2 and 4)."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from mehs.calibration import UNIT_ABSOLUTE
from mehs.calibration.targets import sphere_radiance
from mehs.cube import SpectralCube
from mehs.errors import FormatError
from mehs.io import load_cube
from mehs.io.exr import read_exr, read_exr_spectral, write_exr_spectral
from mehs.io.ssr_kaist import read_kaist

WL = np.arange(420.0, 721.0, 10.0)
EMISSIVE_UNITS = "W.m^-2.sr^-1"  # the Fichet layout's spelling (pbrt-v4, ART, colour-science)


def _public_exr(path, planes: dict, header: dict | None = None):
    """An EXR written with the OpenEXR bindings alone (no mehs attribute), as other tools do."""
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    OpenEXR.File(hdr, {k: np.ascontiguousarray(v, np.float32) for k, v in planes.items()}
                 ).write(str(path))
    return path


def _kaist_like(path):
    """KAIST's layout: w420nm … w720nm reflectance plus R, G, B (Choi et al. 2017)."""
    rng = np.random.default_rng(3)
    cube = rng.uniform(0.02, 0.9, (5, 7, WL.size)).astype(np.float32)
    planes = {f"w{int(w)}nm": cube[..., i] for i, w in enumerate(WL)}
    planes.update({c: cube[..., 0] for c in "RGB"})
    return _public_exr(path, planes), cube


def test_generic_reader_reads_kaist_channel_names(tmp_path):
    f, cube = _kaist_like(tmp_path / "scene01_reflectance.exr")
    c = read_exr_spectral(f)
    np.testing.assert_array_equal(c.wavelengths, WL)
    np.testing.assert_array_equal(c.data, cube)
    assert c.units == "reflectance"
    assert c.metadata["exr_channels"][0] == "w420nm"
    # the same cube as the KAIST reader's (one parser for both)
    k, wl, _ = read_kaist(f)
    np.testing.assert_array_equal(k, c.data)
    np.testing.assert_array_equal(wl, c.wavelengths)
    assert load_cube(f).data.shape == (5, 7, 31)


@pytest.mark.parametrize("names", [("S0.400nm", "S0.410nm", "w400nm", "w410nm"),
                                   ("400nm", "410nm", "w420nm"),
                                   ("T.400nm", "410nm")])
def test_mixed_naming_schemes_are_refused_naming_the_file(tmp_path, names):
    f = _public_exr(tmp_path / "mixed.exr", {n: np.full((2, 3), i + 1.0) for i, n in
                                             enumerate(names)})
    with pytest.raises(FormatError, match="naming scheme") as e:
        read_exr_spectral(f)
    assert "mixed.exr" in str(e.value)


def test_one_wavelength_named_twice_is_refused(tmp_path):
    # 400 nm written three ways: the cube would hold that band three times
    f = _public_exr(tmp_path / "dup.exr", {"S0.400nm": np.ones((2, 2)),
                                           "S0.400,0nm": np.ones((2, 2)) * 2,
                                           "S0.0,4um": np.ones((2, 2)) * 3,
                                           "S0.410nm": np.ones((2, 2))})
    with pytest.raises(FormatError, match="same wavelength") as e:
        read_exr_spectral(f)
    assert "dup.exr" in str(e.value) and "S0.0,4um" in str(e.value)


def test_emissive_and_reflective_pair_still_reads_the_emission(tmp_path):
    # Fichet 2021 allows both in one file; S0 (the light) is the image
    f = _public_exr(tmp_path / "both.exr", {"S0.400nm": np.full((2, 2), 5.0),
                                            "S0.410nm": np.full((2, 2), 6.0),
                                            "T.400nm": np.full((2, 2), 0.5),
                                            "T.410nm": np.full((2, 2), 0.6)})
    c = read_exr_spectral(f)
    assert c.data[0, 0].tolist() == [5.0, 6.0] and c.units == "relative radiance"


def _sphere_cube(units, **kw) -> SpectralCube:
    """The simulator's integrating sphere (W·sr⁻¹·m⁻²·nm⁻¹) on a 3×4 image."""
    wl = np.arange(400.0, 701.0, 10.0)
    data = np.broadcast_to(sphere_radiance(wl), (3, 4, wl.size)).astype(np.float32)
    return SpectralCube(data.copy(), wl, units=units, **kw)


def test_absolute_radiance_carries_fichet_emissive_units(tmp_path):
    from mehs.io.exr import ABSOLUTE_RADIANCE, EMISSIVE_UNITS as written

    assert ABSOLUTE_RADIANCE == UNIT_ABSOLUTE and written == EMISSIVE_UNITS
    cube = _sphere_cube(UNIT_ABSOLUTE)
    f = write_exr_spectral(tmp_path / "abs.exr", cube)
    # the spelling of the Fichet layout (pbrt-v4, ART, colour-science's writer)
    assert read_exr(f).header["emissiveUnits"] == "W.m^-2.sr^-1" == EMISSIVE_UNITS
    back = read_exr_spectral(f)
    assert back.units == UNIT_ABSOLUTE
    np.testing.assert_allclose(back.data[1, 2], sphere_radiance(cube.wavelengths), rtol=1e-6)


def test_relative_or_scaled_radiance_carries_no_emissive_units(tmp_path):
    rel = write_exr_spectral(tmp_path / "rel.exr", _sphere_cube("relative radiance"))
    assert "emissiveUnits" not in read_exr(rel).header
    refl = write_exr_spectral(tmp_path / "refl.exr", _sphere_cube("reflectance"))
    assert "emissiveUnits" not in read_exr(refl).header
    # a dataset cube stores radiance × 2^-4: its values are not W.m^-2.sr^-1
    scaled = _sphere_cube(UNIT_ABSOLUTE, metadata={"mehs radiance scale": "0.0625"})
    f = write_exr_spectral(tmp_path / "scaled.exr", scaled)
    hdr = read_exr(f).header
    assert "emissiveUnits" not in hdr and hdr["mehsRadianceScale"] == 0.0625


def test_radiance_scale_survives_a_read_and_rewrite(tmp_path):
    scaled = _sphere_cube(UNIT_ABSOLUTE, metadata={"mehs radiance scale": "0.0625"})
    f = write_exr_spectral(tmp_path / "a.exr", scaled)
    back = read_exr_spectral(f)
    assert float(back.metadata["mehs radiance scale"]) == 0.0625
    g = write_exr_spectral(tmp_path / "b.exr", back)
    assert read_exr(g).header["mehsRadianceScale"] == 0.0625
    assert "emissiveUnits" not in read_exr(g).header


def test_other_tools_emissive_units_give_the_units(tmp_path):
    planes = {f"S0.{int(w)}nm": np.full((2, 2), 0.01 * (i + 1)) for i, w in enumerate(WL[:4])}
    f = _public_exr(tmp_path / "pbrt.exr", planes, {"spectralLayoutVersion": "1.0",
                                                    "emissiveUnits": "W.m^-2.sr^-1"})
    c = read_exr_spectral(f)
    assert c.units == UNIT_ABSOLUTE and c.metadata["emissiveUnits"] == "W.m^-2.sr^-1"
    # a unit it does not know is reported as written, not taken for relative radiance
    g = _public_exr(tmp_path / "other.exr", planes, {"emissiveUnits": "W.m^-2.sr^-1.um^-1"})
    assert read_exr_spectral(g).units == "W.m^-2.sr^-1.um^-1"
    # and a file without it reads as before
    h = _public_exr(tmp_path / "plain.exr", planes)
    assert read_exr_spectral(h).units == "relative radiance"
