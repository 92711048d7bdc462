"""`mehs paper`: structure of the five tables and the figures (not numbers), resumability."""

import json
import re

import pytest

from mehs.cli import main
from mehs.errors import InputError
from mehs.ssr.paper import plan_runs
from mehs.ssr.registry import Architecture, list_architectures
from mehs.ssr.synthetic import make_paired_set


def test_plan_covers_both_settings_and_both_learning_modes():
    archs = {"a": Architecture("a", build=lambda c: None, learning=("similarity", "e2e")),
             "b": Architecture("b", build=lambda c: None, learning=("e2e",))}
    runs = {r.name: r for r in plan_runs(archs)}
    assert set(runs) == {"a-similarity-pp_on", "a-similarity-pp_off", "a-e2e-pp_on",
                         "b-e2e-pp_on", "b-e2e-pp_off"}
    # the pp-on and pp-off networks of one method share a table row; the other mode is Table 1's
    assert runs["a-similarity-pp_off"].row == runs["a-similarity-pp_on"].row == "a"
    assert runs["a-e2e-pp_on"].row == "a-e2e"


def _table(md: str, title: str) -> list[list[str]]:
    block = md.split(f"### {title}", 1)[1].split("\n\n", 2)[1]
    return [[c.strip() for c in line.strip("|").split("|")] for line in block.splitlines()[2:]]


def test_paper_quick_writes_five_tables_and_resumes(tmp_path, capsys):
    # the networks' rows and their pre-processing columns (without torch: Smits alone)
    pytest.importorskip("torch")
    ds = make_paired_set(tmp_path / "ds", n_scenes=5, size=16, seed=2)
    out = tmp_path / "paper"
    archs = dict(list(list_architectures().items())[:2])   # two methods keep the test short
    argv = ["paper", str(ds), "--out", str(out), "--quick", "--epochs", "1",
            "--timing-size", "32x16", "--no-progress"] + [f"--arch={a}" for a in archs]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    md = (out / "paper.md").read_text()
    assert md in printed
    assert (out / "paper.html").read_text().count("<table>") >= 4
    for n in range(1, 6):
        assert f"### Table {n}" in md
    rows2 = {r[0]: r[1:] for r in _table(md, "Table 2.")}
    rows4 = {r[0]: r[1:] for r in _table(md, "Table 4.")}
    rows5 = {r[0]: r[1:] for r in _table(md, "Table 5.")}
    assert set(rows2) == set(rows4) == set(rows5) == set(archs) | {"smits"}
    assert "### Table 2. DATASET (test split)" in md   # make_paired_set has a test split
    num = re.compile(r"^\**\d+\.\d+\**$")
    for rows in (rows2, rows4):
        # every method in its trained setting: networks in both columns, Smits only without
        assert rows["smits"][:2] == ["–", "–"] and all(num.match(c) for c in rows["smits"][2:])
        for a in archs:
            assert all(num.match(c) for c in rows[a]), (a, rows[a])
    t1 = [r[0] for r in _table(md, "Table 1.")]
    assert sorted(t1) == sorted(f"{r.arch} {'◇' if r.learning == 'similarity' else 'e2e'}"
                                for r in plan_runs(archs) if r.preprocess)
    assert "Table 3 and Figure 10 need the real HDR-HS set" in md
    figs = sorted(p.name for p in (out / "figures").glob("fig9_*.png"))
    assert figs and all(f"]({'figures/' + f})" in md for f in figs)
    state = json.loads((out / "state.json").read_text())
    assert set(state["runs"]) == {r.name for r in plan_runs(archs)}
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*.pt")}
    assert main(argv) == 0                                   # resumes: nothing retrained
    printed = capsys.readouterr().out
    assert printed.count("trained already") == len(state["runs"])
    assert "evaluation main: done already" in printed
    assert stamps == {p: p.stat().st_mtime_ns for p in out.glob("runs/*/*.pt")}


def test_paper_rejects_unknown_names(tmp_path):
    ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=8, seed=2)
    with pytest.raises(InputError, match="not registered"):
        from mehs.ssr.paper import run_paper

        run_paper(ds, tmp_path / "o", archs=["nope"])
    assert main(["paper", str(ds), "--out", str(tmp_path / "o"), "--checkpoint", "x"]) == 2


def test_table5_keeps_a_row_for_a_network_out_of_memory():
    from mehs.ssr.baselines import Smits1999
    from mehs.ssr.results_io import timing_block
    from mehs.ssr.timing import time_models

    class Huge(Smits1999):
        name = "huge"

        def predict(self, rgb):  # like AWAN's image-wide attention on a 2048×1024 image
            if rgb.shape[0] > 16:
                raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to "
                                   "allocate 1099511627776 bytes")
            return super().predict(rgb)

    t = time_models([Smits1999(), Huge()], shape=(32, 64))
    assert t[0]["seconds"] > 0 and t[1]["seconds"] is None
    assert t[1]["error"] == "out of memory (1.02e+03 GiB asked)"
    body = timing_block(t)[2]
    assert body[1][0] == "huge (CPU: out of memory (1.02e+03 GiB asked))" and body[1][1] == "–"

    class Broken(Smits1999):
        name = "broken"

        def predict(self, rgb):
            raise RuntimeError("index out of range: a bug")

    with pytest.raises(RuntimeError, match="a bug"):
        time_models([Broken()], shape=(32, 64))
