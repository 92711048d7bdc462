"""Nothing silently wrong (issue 17): damaged outputs and partial brackets are named, not used.

Defect 3: a dataset file that no longer matches its recorded SHA-256 is rebuilt by
``mehs build`` and refused by ``mehs evaluate``; manifest entries without ``files`` are
refused by ``build`` and ``report``. Defect 5: a bracket whose capture did not finish is
refused by ``fuse`` and ``build`` (naming the exposure, suggesting ``capture --resume``)
unless ``--allow-partial``.
"""

import json
import os
import shutil
from pathlib import Path

import pytest

from mehs.cli import main
from mehs.dataset import manifest as mf
from mehs.dataset.build import build_dataset
from mehs.dataset.quality import QualityRules
from mehs.errors import FormatError

SIZE = 24
RULES = QualityRules(min_dynamic_range_stops=0.0)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("scenes")
    out = []
    for i, kind in enumerate(("colorchecker", "window")):
        sim = simulate_bracket(make_scene(kind, SIZE, SIZE, seed=i), SensorModel(seed=3),
                               (0.05, 0.4, 3.2), seed=i)
        out.append(write_simulated_scene(sim, root / f"s{i}", scene_id=f"s{i}"))
    return out


@pytest.fixture(scope="module")
def curve(tmp_path_factory):
    from mehs.synthesis.response import ResponseCurve

    return ResponseCurve.linear(12).save(tmp_path_factory.mktemp("curve") / "linear.json")


@pytest.fixture(scope="module")
def built(scenes, curve, tmp_path_factory):
    ds = tmp_path_factory.mktemp("built") / "ds"
    build_dataset(scenes, ds, workers=1, seed=1, rules=RULES, progress=False, response=curve,
                  splits="0,0,1")
    return ds


@pytest.fixture()
def dataset(built, tmp_path):
    """A private copy of the built dataset (copy2 keeps the mtimes the build recorded)."""
    return Path(shutil.copytree(built, tmp_path / "ds"))


def _flip_byte(path: Path, offset: int = 100, *, keep_mtime: bool = False) -> None:
    st = path.stat()
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    if keep_mtime:
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_rebuild_replaces_a_corrupted_output(dataset, scenes, curve, capsys):
    hs = dataset / "scenes" / "s0" / "hs.dat"
    good = hs.read_bytes()
    _flip_byte(hs)
    capsys.readouterr()
    commits = []
    build_dataset(scenes, dataset, workers=1, seed=1, rules=RULES, progress=False,
                  response=curve, splits="0,0,1", on_commit=commits.append)
    err = capsys.readouterr().err
    assert "scene 's0'" in err and "scenes/s0/hs.dat" in err and "SHA-256" in err
    assert [c["id"] for c in commits] == ["s0"]  # only the damaged scene is rebuilt
    assert hs.read_bytes() == good


def test_truncated_output_is_named_without_hashing(dataset, scenes, curve, capsys):
    ldr = dataset / "scenes" / "s1" / "ldr_rgb.png"
    with open(ldr, "r+b") as fh:
        fh.truncate(ldr.stat().st_size - 1)
    rc = main(["evaluate", str(dataset), "--models", "smits", "--out",
               str(dataset.parent / "res"), "--preprocess", "off", "--split", "all"])
    err = capsys.readouterr().err
    assert rc == 2 and "scene 's1'" in err and "ldr_rgb.png" in err and "bytes" in err
    assert not (dataset.parent / "res" / "evaluation.json").exists()


def test_evaluate_refuses_a_corrupted_dataset(dataset, capsys):
    _flip_byte(dataset / "scenes" / "s1" / "hs.dat", 64)
    res = dataset.parent / "res"
    rc = main(["evaluate", str(dataset), "--models", "smits", "--out", str(res),
               "--preprocess", "off", "--split", "all"])
    err = capsys.readouterr().err
    assert rc == 2 and "scene 's1'" in err and "scenes/s1/hs.dat" in err and "SHA-256" in err
    assert not (res / "evaluation.json").exists()


def test_same_mtime_corruption_needs_verify(dataset, capsys):
    """The stat check is a cache; --verify hashes everything (and catches what it cannot)."""
    _flip_byte(dataset / "scenes" / "s1" / "hs.dat", 64, keep_mtime=True)
    res = dataset.parent / "res"
    common = [str(dataset), "--models", "smits", "--preprocess", "off", "--split", "all"]
    assert main(["evaluate", *common, "--out", str(res)]) == 0  # documented limit of the cache
    capsys.readouterr()
    assert main(["evaluate", *common, "--out", str(res), "--verify", "--force"]) == 2
    assert "scenes/s1/hs.dat" in capsys.readouterr().err


def test_copied_dataset_is_hashed_once_and_accepted(dataset, tmp_path):
    """New mtimes (a plain copy) force a hash, which passes: no false alarm."""
    from mehs.ssr.data import load_pairs

    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy, copy_function=shutil.copyfile)
    assert len(load_pairs(copy)) == 2


@pytest.mark.parametrize("key", ["files", "sha256"])
def test_entry_without_files_is_refused(dataset, scenes, curve, key):
    m = json.loads((dataset / mf.MANIFEST_NAME).read_text())
    del m["scenes"][0][key]
    (dataset / mf.MANIFEST_NAME).write_text(json.dumps(m))
    before = (dataset / mf.MANIFEST_NAME).read_bytes()
    with pytest.raises(FormatError, match=f"scene 's0': '{key}' is missing"):
        build_dataset(scenes, dataset, workers=1, seed=1, rules=RULES, progress=False,
                      response=curve, splits="0,0,1")
    assert (dataset / mf.MANIFEST_NAME).read_bytes() == before  # not rewritten
    assert main(["report", str(dataset)]) == 2
    assert not (dataset / "report.html").exists()


# ------------------------------------------------------------------ partial brackets

def _mark_incomplete(scene: Path, dst: Path, k: int = 2) -> Path:
    shutil.copytree(scene, dst)
    doc = json.loads((dst / "scene.json").read_text())
    rec = doc["exposures"][k]
    rec["status"] = "incomplete"
    rec["files"] = {}
    (dst / "scene.json").write_text(json.dumps(doc))
    return dst


def test_fuse_refuses_a_partial_bracket(scenes, tmp_path, capsys):
    scene = _mark_incomplete(scenes[0], tmp_path / "partial")
    out = tmp_path / "fused"
    assert main(["fuse", str(scene), "--out", str(out), "--response", "linear"]) == 2
    err = capsys.readouterr().err
    assert "exposure 2 (3.2 ms, exposures/2_3.2ms) is incomplete" in err
    assert "mehs capture --resume" in err and "--allow-partial" in err
    assert not (out / "radiance.hdr").exists()
    assert main(["fuse", str(scene), "--out", str(out), "--response", "linear",
                 "--allow-partial"]) == 0
    assert json.loads((out / "summary.json").read_text())["exposure_ratios"] == [1.0, 8.0]


def test_fuse_refuses_a_planned_exposure_never_started(scenes, tmp_path, capsys):
    scene = tmp_path / "planned"
    shutil.copytree(scenes[0], scene)
    doc = json.loads((scene / "scene.json").read_text())
    doc["plan"] = {"times_ms": [0.05, 0.4, 3.2, 25.6]}
    (scene / "scene.json").write_text(json.dumps(doc))
    assert main(["fuse", str(scene), "--out", str(tmp_path / "f"), "--response", "linear"]) == 2
    assert "exposure 3 (25.6 ms, not started)" in capsys.readouterr().err


def test_build_refuses_a_partial_bracket_unless_allowed(scenes, curve, tmp_path, capsys):
    scene = _mark_incomplete(scenes[0], tmp_path / "partial")
    ds = tmp_path / "ds"
    m = build_dataset([scene], ds, workers=1, rules=RULES, progress=False, response=curve)
    (e,) = m["scenes"]
    assert e["status"] == "fail" and "exposure 2" in e["error"] and "--resume" in e["error"]
    assert main(["build", str(scene), "--out", str(ds), "--response", str(curve),
                 "--quiet", "--min-dr", "0"]) == 1
    assert main(["build", str(scene), "--out", str(ds), "--response", str(curve), "--quiet",
                 "--min-dr", "0", "--allow-partial"]) == 0
    (e,) = mf.read_manifest(ds)["scenes"]
    assert e["status"] == "pass" and e["quality"]["n_exposures"] == 2


# ------------------------------------------------------------------ model files (defect 4)

@pytest.mark.parametrize("name,content,says", [
    ("empty.npz", b"", "not a regression model file (EOFError"),
    ("zip.npz", b"PK\x03\x04garbage", "not a regression model file (BadZipFile"),
    ("user.py:f", b"x\n", "running"),
    ("syntax.py:f", b"def f(:\n", "SyntaxError"),
])
def test_broken_model_file_is_a_named_error(built, tmp_path, capsys, name, content, says):
    fname = name.split(":")[0]
    (tmp_path / fname).write_bytes(content)
    model = str(tmp_path / name)
    rc = main(["evaluate", str(built), "--models", model, "--out", str(tmp_path / "res"),
               "--split", "all"])
    err = capsys.readouterr().err
    assert rc == 2 and says in err and fname in err


# ------------------------------------------------------------------ one overwrite rule (10)

def test_derived_output_commands_share_one_overwrite_rule(built, scenes, tmp_path, capsys):
    fused, res, hs = tmp_path / "fused", tmp_path / "res", tmp_path / "hs.hdr"
    runs = {
        "fuse": ["fuse", str(scenes[0]), "--out", str(fused), "--response", "linear"],
        "evaluate": ["evaluate", str(built), "--models", "smits", "--out", str(res),
                     "--preprocess", "off", "--split", "all"],
    }
    for argv in runs.values():
        assert main(argv) == 0
    runs["resample"] = ["resample", str(fused / "radiance.hdr"), str(hs)]
    runs["rgb"] = ["rgb", str(hs), "--out", str(tmp_path / "rgb"), "--float"]
    runs["export"] = ["export", str(hs), "--out", str(tmp_path / "exr"), "--format", "spectral"]
    for name in ("resample", "rgb", "export"):
        assert main(runs[name]) == 0, name
    for name, argv in runs.items():
        before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}
        capsys.readouterr()
        assert main(argv) == 2, name
        assert "use --force to replace it" in capsys.readouterr().err, name
        after = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}
        assert after == before, name  # refused before anything was written
        assert main(argv + ["--force"]) == 0, name


# ------------------------------------------------------------------ splits (10)

def test_adding_scenes_names_the_scenes_that_change_split(scenes, curve, tmp_path, capsys):
    from mehs.dataset.splits import make_splits, parse_fractions

    fr = parse_fractions("0.5,0,0.5")

    def split(ids, seed):
        return {i: n for n, v in make_splits(ids, fr, seed).items() for i in v}

    # a seed under which adding s1 moves s0 (the cut at round(n/2) moves with n)
    seed = next(k for k in range(100) if split(["s0"], k)["s0"] != split(["s0", "s1"], k)["s0"])
    ds = tmp_path / "ds"
    kw = dict(workers=1, seed=seed, rules=RULES, progress=False, response=curve, splits=fr)
    build_dataset(scenes[:1], ds, **kw)
    before = split(["s0"], seed)["s0"]
    capsys.readouterr()
    m = build_dataset(scenes, ds, **kw)
    after = next(n for n, v in m["splits"].items() if "s0" in v)
    assert after != before
    assert f"s0 {before} → {after}" in capsys.readouterr().err
    build_dataset(scenes, ds, **kw)  # nothing moves: nothing said
    assert "changed split" not in capsys.readouterr().err


def test_rebuild_removes_temp_files_of_killed_atomic_writes(dataset, scenes, curve):
    """A SIGKILL between an atomic write and its rename leaves ``.<name>.*.part*``."""
    left = [dataset / ".manifest.json.k1ll.part.json", dataset / "splits" / ".test.txt.k1ll.part.txt"]
    for f in left:
        f.write_text("half")
    build_dataset(scenes, dataset, workers=1, seed=1, rules=RULES, progress=False,
                  response=curve, splits="0,0,1")
    assert not [f for f in left if f.exists()]
