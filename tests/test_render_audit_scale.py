"""A dataset cube's radiance scale (stored = radiance × 2^-k) is undone when it lights a scene.

Truth: the cube's own radiance (what the dataset build multiplied by 2^-k to fit half floats,
design.md §6 / docs/formats.md) — the map must emit that, whichever file layout carries it.
"""

import json

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.export import export_per_wavelength, export_spectral_exr
from mehs.io.envi import write_envi
from mehs.render.maps import load_envmap
from mehs.rgb import WAVELENGTHS_31


@pytest.fixture
def scaled(tmp_path):
    """The same map (true radiance ``truth``) in the three layouts, stored × 0.25."""
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.5, 4.0, (4, 8, WAVELENGTHS_31.size)).astype(np.float32)
    cube = SpectralCube(data=truth * np.float32(0.25), wavelengths=WAVELENGTHS_31,
                        units="radiance", metadata={"mehs radiance scale": repr(0.25)})
    write_envi(tmp_path / "hs.hdr", cube, dtype=np.float32)
    export_per_wavelength(cube, tmp_path / "pw")
    export_spectral_exr(cube, tmp_path / "hs.exr")
    return truth, tmp_path


@pytest.mark.parametrize("name", ["hs.hdr", "pw", "hs.exr"])
def test_map_from_a_scaled_dataset_cube_emits_its_radiance(scaled, name):
    truth, root = scaled
    env = load_envmap(root / name)
    # before: the map held truth × 0.25 and said nothing about it
    np.testing.assert_array_equal(env.radiance, truth)
    assert env.metadata["radiance_scale"] == 0.25


def test_unscaled_map_is_read_as_is_and_a_bad_scale_names_the_file(tmp_path):
    data = np.full((3, 4, WAVELENGTHS_31.size), 2.0, np.float32)
    export_per_wavelength(SpectralCube(data=data, wavelengths=WAVELENGTHS_31,
                                       units="relative radiance"), tmp_path)
    env = load_envmap(tmp_path)
    np.testing.assert_array_equal(env.radiance, data)
    assert env.metadata["radiance_scale"] is None
    listing = tmp_path / "band_wavelengths.json"
    doc = json.loads(listing.read_text())
    doc["radiance_scale"] = -1
    listing.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="band_wavelengths.json.*radiance scale"):
        load_envmap(tmp_path)


def test_reflectance_cube_is_refused_as_a_light_naming_the_file(tmp_path):
    # a Specim IQ REFLECTANCE_* result or a T.<λ>nm EXR is a ratio to the white
    # reference, not radiance: it was accepted and lit the scene with the white panel
    cube = SpectralCube(data=np.full((3, 4, WAVELENGTHS_31.size), 0.5, np.float32),
                        wavelengths=WAVELENGTHS_31, units="reflectance")
    export_spectral_exr(cube, tmp_path / "refl.exr")
    export_per_wavelength(cube, tmp_path / "pw")
    with pytest.raises(InputError, match=r"refl\.exr.*reflectance.*not light"):
        load_envmap(tmp_path / "refl.exr")
    with pytest.raises(InputError, match=r"band_wavelengths\.json.*reflectance"):
        load_envmap(tmp_path / "pw")


def test_render_json_records_the_map_units_and_the_scale_divided_out(scaled, tmp_path):
    pytest.importorskip("mitsuba")
    from mehs.render.run import render_comparison
    from mehs.render.scene import RenderSettings

    truth, root = scaled
    s = RenderSettings(width=4, height=4, spp=1, material="diffuse", bands=(450.0, 550.0, 650.0))
    doc = render_comparison(root / "hs.hdr", tmp_path / "out", s, methods=(), progress=False)
    assert doc["map"]["units"] == "radiance"
    assert doc["map"]["stored_radiance_scale"] == 0.25
