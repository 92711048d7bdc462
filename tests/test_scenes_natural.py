"""Natural scenes (issue 14 "Must show"): diversity of a 256×256 scene, disjoint pools, physics."""

from __future__ import annotations

import numpy as np
import pytest

from mehs.rgb import WAVELENGTHS_31
from mehs.scenes.diversity import format_diversity, spectral_diversity
from mehs.scenes.library import (LIGHT_FAMILIES, POOLS, light_pool, material_library,
                                 material_pools)
from mehs.scenes.natural import make_natural_scene


@pytest.fixture(scope="module")
def scene256():
    return make_natural_scene(256, wavelengths=WAVELENGTHS_31, seed=1, lighting="mixed", pool="test")


def test_256_scene_has_200_materials_and_8_components(scene256, capsys):
    s = scene256
    d = spectral_diversity(s.radiance)
    d["n_materials"] = s.info["n_materials"]
    print(format_diversity(d, title="natural scene 256×256, test pool"))
    out = capsys.readouterr().out
    assert "components for 99 % of the variance" in out
    # 200+ distinct region materials (measured samples and their mixtures) from the 80 samples
    # of the test pool, nearly all of them used
    assert s.info["n_materials"] >= 200 and len(s.info["materials"]) >= 60
    assert d["pcs_99"] >= 8
    # far more distinct spectra than a ColorChecker scene's 24 patches
    assert d["distinct_spectra"] > 500


def test_pools_are_disjoint_and_cover_every_family():
    names, table = material_library(WAVELENGTHS_31)
    assert len(names) >= 300 and table.shape == (len(names), 31)
    assert np.all((table >= 0) & (table <= 1))
    pools = material_pools()
    sets = [set(pools[p].tolist()) for p in POOLS]
    assert not (sets[0] & sets[1] or sets[0] & sets[2] or sets[1] & sets[2])
    assert set().union(*sets) == set(range(len(names)))
    for fam in LIGHT_FAMILIES:
        members = [light_pool(fam, p) for p in POOLS]
        assert all(members), fam
        keys = [{str(m) for m in ms} for ms in members]
        assert not (keys[0] & keys[1] or keys[0] & keys[2] or keys[1] & keys[2]), fam


def test_test_scene_uses_only_test_pool_materials(scene256):
    names, _ = material_library(WAVELENGTHS_31)
    test = {f"{names[i][0]}/{names[i][1]}" for i in material_pools()["test"]}
    assert set(scene256.info["materials"]) <= test
    for light in scene256.info["lights"]:
        pooled = light_pool(light["family"], "test")
        if light["kelvin"] is None:
            assert any(getattr(m, "name", None) == light["name"] for m in pooled)
        else:
            assert any(isinstance(m, tuple) and m[0] <= light["kelvin"] <= m[1] for m in pooled)


def test_reproducible_hdr_and_highlights_carry_the_light():
    a = make_natural_scene(48, wavelengths=WAVELENGTHS_31, seed=5, lighting="tungsten",
                           source_ratio=5000.0)
    b = make_natural_scene(48, wavelengths=WAVELENGTHS_31, seed=5, lighting="tungsten",
                           source_ratio=5000.0)
    np.testing.assert_array_equal(a.radiance, b.radiance)
    r = a.radiance
    assert np.all(np.isfinite(r)) and r.min() >= 0
    # the lamp in view is 5000× the diffuse white: a dynamic range far beyond 8 bits
    lum = r.mean(axis=2)
    assert lum.max() / np.percentile(lum[lum > 0], 5) > 1e4
    c = make_natural_scene(48, wavelengths=WAVELENGTHS_31, seed=6, lighting="daylight",
                           source_ratio=0.0, motion=True)
    assert c.moving and c.moved_mask(3).any()
    assert c.info["lights"][0]["family"] == "sun" and c.info["lights"][1]["family"] == "sky"


def test_bad_arguments_are_clear_errors():
    from mehs.errors import InputError

    with pytest.raises(InputError, match="pool"):
        make_natural_scene(16, pool="holdout")
    with pytest.raises(InputError, match="lighting"):
        make_natural_scene(16, lighting="candle")
    with pytest.raises(InputError, match="8×8"):
        make_natural_scene(4)


def test_paired_set_from_natural_scenes_uses_split_pools(tmp_path):
    import json

    from mehs.ssr.synthetic import make_paired_set

    p = make_paired_set(tmp_path / "ps", n_scenes=3, size=16, seed=2, generator="natural")
    m = json.loads((p / "manifest.json").read_text())
    split_of = {sid: k for k, v in m["splits"].items() for sid in v}
    for s in m["scenes"]:
        assert s["provenance"]["pool"] == split_of[s["id"]]


def test_dataset_diversity_held_out_split_is_farther_than_colorchecker(tmp_path, capsys):
    import json

    from mehs.ssr.diversity import dataset_diversity, main
    from mehs.ssr.synthetic import make_paired_set

    cc = make_paired_set(tmp_path / "cc", n_scenes=5, size=24, seed=1)
    nat = make_paired_set(tmp_path / "nat", n_scenes=5, size=24, seed=1, generator="natural")
    d_cc = dataset_diversity(cc, per_scene=400)
    d_nat = dataset_diversity(nat, per_scene=400)
    assert d_cc["reference"] == d_nat["reference"] == "train"
    # disjoint pools: the held-out scenes lie farther from anything trained on than
    # ColorChecker scenes do (same 24 patches in every split)
    assert d_nat["nn_angle_median"] > 2 * d_cc["nn_angle_median"]
    # noise-free scenes: the noise test measured them and excluded few of their pixels
    # (24×24 scenes change from pixel to pixel: 4 % here)
    assert d_nat["noise_source"] == ["neighbours"] * d_nat["scenes"]
    assert d_nat["excluded_noise_fraction"] < 0.1 and d_nat["pixels_total"] > 0
    assert d_nat["reference_pixels_total"] > 0 and "reference_excluded_noise" in d_nat
    out = tmp_path / "div.json"
    assert main([str(nat), "--per-scene", "200", "--angle", "2", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nearest training pixel, median angle" in text
    assert "below the noise (angular noise > 1°), excluded" in text
    rec = json.loads(out.read_text())
    assert rec["noise_angle_deg"] == 1.0 and rec["angle_deg"] == 2.0
    assert {"excluded_noise", "excluded_noise_fraction", "reference_excluded_noise"} <= set(rec)


def test_capture_simulate_natural_scene(tmp_path, capsys):
    import json

    from mehs.cli import main

    out = tmp_path / "n1"
    assert main(["capture", "--simulate", "--scene", "natural", "--lighting", "sodium",
                 "--pool", "test", "--size", "16", "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    info = doc["device"]["scene"]
    assert info["kind"] == "natural" and info["pool"] == "test" and info["lighting"] == "sodium"
    assert info["lights"][0]["family"] == "sodium" and doc["truth"] == "truth/radiance.hdr"
    assert "3 of 3 exposures complete" in capsys.readouterr().out
