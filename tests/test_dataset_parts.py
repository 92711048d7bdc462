"""Dataset builder pieces that need no synthesis stage: manifest, splits, rules, scene lists, runner."""

import json
import os

import pytest

from mehs.dataset import manifest as mf
from mehs.dataset.build import _Lock, _place
from mehs.dataset.parallel import report_stage, run_tasks
from mehs.dataset.quality import QualityRules, judge
from mehs.dataset.scene_list import collect_scenes, read_scene_list_csv, read_scene_list_toml
from mehs.dataset.splits import make_splits, parse_fractions, write_split_files
from mehs.errors import FormatError, InputError


def _entry(sid, status="pass", **q):
    return {"id": sid, "status": status, "reasons": [], "files": {"hs": f"scenes/{sid}/hs.hdr"},
            "sha256": {}, "quality": q, "key": "k" + sid,
            "provenance": {"run": {"started": "now", "seconds": 1.0}, "kind": "scene"}}


def test_manifest_roundtrip_sorted_and_index(tmp_path):
    m = mf.new_manifest(software_version="0", wavelengths=range(400, 701, 10), rgb={"a": "b"})
    m["scenes"] = [_entry("b", dynamic_range_stops=10.5, exposure_ratios=[1.0, 4.0]), _entry("a")]
    m["splits"] = {"train": ["a"], "val": ["b"], "test": []}
    mf.write_manifest(tmp_path, m)
    back = mf.read_manifest(tmp_path)
    assert [s["id"] for s in back["scenes"]] == ["a", "b"]
    rows = (tmp_path / "index.csv").read_text().splitlines()
    assert rows[0].split(",") == list(mf.INDEX_COLUMNS)
    assert rows[2].startswith("b,pass,val,,10.5,") and "1 4" in rows[2]
    assert not list(tmp_path.glob(".*part*"))  # atomic writes left no temp files


def test_manifest_rejects_other_formats(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "other/1", "scenes": []}))
    with pytest.raises(FormatError, match="mehs-dataset/1"):
        mf.read_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(FormatError, match="JSON"):
        mf.read_manifest(tmp_path)
    with pytest.raises(FormatError, match="no dataset manifest"):
        mf.read_manifest(tmp_path / "nothing")


def test_strip_volatile_and_key():
    m = {"scenes": [_entry("a")]}
    s = mf.strip_volatile(m)
    assert "run" not in s["scenes"][0]["provenance"] and "run" in m["scenes"][0]["provenance"]
    k = mf.scene_key({"a": "1"}, {"m": 1}, "0.1")
    assert k == mf.scene_key({"a": "1"}, {"m": 1}, "0.1")
    assert k != mf.scene_key({"a": "2"}, {"m": 1}, "0.1")
    assert k != mf.scene_key({"a": "1"}, {"m": 2}, "0.1")
    assert k != mf.scene_key({"a": "1"}, {"m": 1}, "0.2")


def test_splits_deterministic_exact_and_order_free(tmp_path):
    ids = [f"s{i:02d}" for i in range(20)]
    a = make_splits(ids, (0.7, 0.15, 0.15), seed=3)
    assert a == make_splits(list(reversed(ids)), "0.7,0.15,0.15", seed=3)
    assert [len(a[k]) for k in ("train", "val", "test")] == [14, 3, 3]
    assert sorted(sum(a.values(), [])) == ids
    assert a != make_splits(ids, (0.7, 0.15, 0.15), seed=4)
    # adding one scene moves at most a couple of the others
    b = make_splits(ids + ["s99"], (0.7, 0.15, 0.15), seed=3)
    moved = sum(1 for k in a for s in a[k] if s not in b[k])
    assert moved <= 2
    write_split_files(tmp_path, a)
    assert (tmp_path / "splits" / "val.txt").read_text().split() == a["val"]
    for bad in ("0.5,0.5", "0.7,0.2,0.2", "a,b,c", "-0.1,0.6,0.5"):
        with pytest.raises(InputError):
            parse_fractions(bad)


def test_quality_rules():
    ok = {"ghost_fraction": 0.0, "saturated_fraction": 0.001, "invalid_fraction": 0.0,
          "dynamic_range_stops": 12.0, "n_exposures": 3}
    assert judge(ok) == ("pass", [])
    st, why = judge({**ok, "ghost_fraction": 0.05})
    assert st == "fail" and "ghost fraction" in why[0]
    st, why = judge({**ok, "dynamic_range_stops": 2.0, "saturated_fraction": 0.2})
    assert st == "fail" and len(why) == 2
    assert judge({**ok, "ghost_fraction": 0.05}, QualityRules(max_ghost_fraction=0.1))[0] == "pass"
    assert judge({}, error="boom") == ("fail", ["synthesis failed: boom"])
    assert judge({"ghost_fraction": None, "dynamic_range_stops": None}) == ("pass", [])
    assert judge({**ok, "n_exposures": 1})[0] == "fail"


def _specim_dirs(root, names):
    for n in names:
        (root / n / "capture").mkdir(parents=True)
        (root / n / "capture" / "x.raw").write_bytes(b"x")


def test_scene_lists_csv_toml_and_folders(tmp_path):
    _specim_dirs(tmp_path, ["a1", "a2", "a3"])
    csv = tmp_path / "list.csv"
    csv.write_text("# lab scenes\nscene_id, folder_short, folder_mid, folder_long, note\n"
                   "lab1, a1, a2, a3, sunny\n\n")
    (s,) = read_scene_list_csv(csv)
    assert s.scene_id == "lab1" and s.kind == "specim"
    assert s.paths == tuple(str((tmp_path / n).resolve()) for n in ("a1", "a2", "a3"))
    toml = tmp_path / "list.toml"
    toml.write_text('[[scene]]\nid = "lab2"\nfolders = ["a1", "a3"]\n')
    (t,) = read_scene_list_toml(toml)
    assert t.scene_id == "lab2" and len(t.paths) == 2
    for d in ("sc1", "sc2"):
        (tmp_path / "scenes" / d).mkdir(parents=True)
        (tmp_path / "scenes" / d / "scene.json").write_text(json.dumps({"scene_id": d.upper()}))
    got = collect_scenes([tmp_path / "scenes", csv, toml])
    assert [g.scene_id for g in got] == ["SC1", "SC2", "lab1", "lab2"]
    with pytest.raises(InputError, match="given twice"):
        collect_scenes([csv, csv])
    bad = tmp_path / "bad.csv"
    bad.write_text("scene_id,folder_short\nx,a1\n")
    with pytest.raises(InputError, match="lacks column"):
        read_scene_list_csv(bad)
    bad.write_text("scene_id,folder_short,folder_mid,folder_long\nx,a1,a2,missing\n")
    with pytest.raises(InputError, match="not found"):
        read_scene_list_csv(bad)
    bad.write_text("scene_id,folder_short,folder_mid,folder_long\n../x,a1,a2,a3\n")
    with pytest.raises(InputError, match="folder name"):
        read_scene_list_csv(bad)
    with pytest.raises(InputError, match="no such"):
        collect_scenes([tmp_path / "nope"])


def _square(x):
    report_stage(str(x), "squaring")
    return x * x


@pytest.mark.parametrize("workers", [1, 2])
def test_runner_bounded_results_and_stages(workers):
    seen = []
    out = list(run_tasks(_square, [(str(i), i) for i in range(5)], workers=workers,
                         on_stage=lambda t, s: seen.append((t, s))))
    assert sorted(out) == [0, 1, 4, 9, 16]
    if workers == 1:
        assert ("3", "squaring") in seen
    else:
        assert any(s == "queued" for _, s in seen)


def test_runner_dask_local_cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(processes=False, n_workers=1, threads_per_worker=2,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        out = list(run_tasks(_square, [(str(i), i) for i in range(4)], workers=2,
                             scheduler=client))
    assert sorted(out) == [0, 1, 4, 9]


def test_lock_and_place(tmp_path):
    with _Lock(tmp_path):
        with pytest.raises(InputError, match="another 'mehs build'"):
            with _Lock(tmp_path):
                pass
    assert not (tmp_path / ".mehs-build.lock").exists()
    # a lock left by a dead process is taken over
    (tmp_path / ".mehs-build.lock").write_text(f"999999999 {os.uname().nodename}\n")
    with _Lock(tmp_path):
        pass
    sc = tmp_path / "scenes"
    (sc / ".tmp-a").mkdir(parents=True)
    (sc / ".tmp-a" / "f").write_text("new")
    (sc / "a").mkdir()
    (sc / "a" / "f").write_text("old")
    _place(sc, "a", built=True)
    assert (sc / "a" / "f").read_text() == "new" and sorted(p.name for p in sc.iterdir()) == ["a"]
    _place(sc, "a", built=False)
    assert not (sc / "a").exists()
