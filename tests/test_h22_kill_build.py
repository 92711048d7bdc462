"""A rebuild (``--force``, new parameters) killed while it replaces a listed scene's folder.

``_place`` moves ``scenes/<id>`` aside and the new build in; the manifest is written after.
Killed in between, the manifest on disk used to list the scene while its files were gone
(moved aside, removed by the next run) or were the new build's under the old hashes.
"""

import hashlib
import os

import pytest

from mehs.dataset import build as b
from mehs.dataset import manifest as mf
from mehs.dataset.build import build_dataset
from mehs.dataset.quality import QualityRules

LAX = QualityRules(max_ghost_fraction=1, max_saturated_fraction=1, max_invalid_fraction=1,
                   min_dynamic_range_stops=0, max_response_uncertainty=1)


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it in the build runs (no commit)."""


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("rebuild")
    out = []
    for i in range(2):
        sim = simulate_bracket(make_scene("colorchecker", 10, 5, seed=i), SensorModel(seed=3),
                               (0.1, 0.8, 6.4), seed=i)
        out.append(write_simulated_scene(sim, root / f"s{i}", scene_id=f"s{i}"))
    from mehs.synthesis.response import ResponseCurve

    return out, ResponseCurve.linear(12).save(root / "linear.json")   # no curve recovery


def _listed_scenes_are_whole(ds):
    m = mf.read_manifest(ds)
    for e in m["scenes"]:
        for key, digest in e["sha256"].items():
            rel = e["files"][key]
            p = ds / rel
            assert p.is_file(), f"manifest lists {e['id']} but {rel} is missing"
            assert hashlib.sha256(p.read_bytes()).hexdigest() == digest, f"{rel} is stale"


@pytest.mark.parametrize("after", ["aside", "in"])
def test_a_rebuild_killed_while_replacing_a_scene_lists_no_missing_or_stale_files(
        scenes, tmp_path, monkeypatch, after):
    scenes, curve = scenes
    ds = tmp_path / "ds"
    build_dataset(scenes, ds, workers=1, progress=False, rules=LAX, response=curve)
    real = os.replace

    def dying_replace(src, dst, *a, **kw):
        real(src, dst, *a, **kw)
        name = os.path.basename(str(dst))
        if (after == "aside" and name.startswith(b.OLD_PREFIX)) or (
                after == "in" and os.path.basename(str(src)).startswith(b.TMP_PREFIX)):
            raise Killed

    monkeypatch.setattr(b.os, "replace", dying_replace)
    with pytest.raises(Killed):
        build_dataset(scenes, ds, workers=1, progress=False, rules=LAX, seed=7, force=True,
                      method="robertson", response=curve)
    monkeypatch.setattr(b.os, "replace", real)
    _listed_scenes_are_whole(ds)
    # and the same command finishes it
    build_dataset(scenes, ds, workers=1, progress=False, rules=LAX, seed=7, force=True,
                  method="robertson", response=curve)
    _listed_scenes_are_whole(ds)
    assert sorted(e["id"] for e in mf.read_manifest(ds)["scenes"]) == ["s0", "s1"]
