"""`mehs evaluate` killed while it writes its results folder (fix in mehs/ssr/results_io.py).

``evaluation.json`` (what the overwrite check and the report read) used to be written
first: a run killed before its tables left a folder the same command refused to finish,
and a ``--force`` run killed there left the new evaluation.json beside the earlier tables.
"""

import pytest

import mehs.io.atomic as atomic
from mehs.cli import main
from mehs.dataset.build import build_dataset
from mehs.dataset.quality import QualityRules

LAX = QualityRules(max_ghost_fraction=1, max_saturated_fraction=1, max_invalid_fraction=1,
                   min_dynamic_range_stops=0, max_response_uncertainty=1)


class Killed(BaseException):
    """Stands for SIGKILL."""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("evalkill")
    scenes = []
    for i in range(2):
        sim = simulate_bracket(make_scene("colorchecker", 10, 6, seed=i), SensorModel(seed=3),
                               (0.1, 0.8, 6.4), seed=i)
        scenes.append(write_simulated_scene(sim, root / f"s{i}", scene_id=f"s{i}"))
    from mehs.synthesis.response import ResponseCurve

    curve = ResponseCurve.linear(12).save(root / "linear.json")
    build_dataset(scenes, root / "ds", workers=1, progress=False, rules=LAX,
                  splits=(0.5, 0.0, 0.5), response=curve)
    return root / "ds"


def test_an_evaluation_killed_writing_its_tables_is_finished_by_the_same_command(
        dataset, tmp_path, monkeypatch):
    out = tmp_path / "ev"
    args = ["evaluate", str(dataset), "--models", "smits", "--out", str(out)]
    real = atomic.write_text_atomic

    def dying(path, *a, **kw):
        if str(path).endswith("tables.txt"):
            raise Killed
        return real(path, *a, **kw)

    monkeypatch.setattr(atomic, "write_text_atomic", dying)
    with pytest.raises(Killed):
        main(args)
    monkeypatch.undo()
    assert not (out / "evaluation.json").exists()      # the tables are not all there
    assert main(args) == 0
    assert (out / "evaluation.json").is_file() and (out / "tables.txt").is_file()


def test_a_forced_evaluation_killed_writing_its_figures_leaves_no_commit_point(dataset, tmp_path,
                                                                        monkeypatch):
    # --force over a finished evaluation, killed while its figures are written: the earlier
    # evaluation.json must not stay to list this run's half-written figures folder
    import mehs.ssr.results_io as results_io

    out = tmp_path / "ev"
    args = ["evaluate", str(dataset), "--models", "smits", "--out", str(out)]
    assert main(args) == 0 and (out / "evaluation.json").is_file()

    def dying(*a, **kw):
        raise Killed

    monkeypatch.setattr(results_io, "write_npz", dying)   # the first figure file of the run
    with pytest.raises(Killed):
        main(args + ["--force"])
    monkeypatch.undo()
    assert not (out / "evaluation.json").exists()
    assert main(args) == 0                              # finished without --force
