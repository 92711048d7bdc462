"""A user model that declares nothing is not scored where its output has no defined meaning.

With pre-processing on and restoration off, the pipeline maps a model's output back with
the inverse Reinhard: right for a fixed method run on tone-mapped RGB, wrong for a model
whose output is absolute spectra. A model that declares nothing cannot say which, and the
paper scores each model only in the setting it was trained for ("–" elsewhere).
"""

import json
import textwrap

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.ssr.scoring import evaluate
from mehs.ssr.synthetic import make_paired_set

USER = textwrap.dedent("""
    import numpy as np
    A = (np.random.default_rng(5).random((31, 3)) * 0.5).astype(np.float32)

    def linear(rgb):
        return np.einsum("bc,hwc->hwb", A, rgb).astype(np.float32)
""")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_paired_set(tmp_path_factory.mktemp("und") / "ds", n_scenes=2, size=24, seed=3)


@pytest.fixture
def user(tmp_path):
    p = tmp_path / "undeclared.py"
    p.write_text(USER)
    return f"{p}:linear"


def test_undeclared_model_gets_no_row_with_preprocessing_on_and_restoration_off(
        dataset, user, tmp_path):
    # the inverse Reinhard made that row MRAE 149 (the other three: about 1)
    res = evaluate(dataset, [user], preprocess="both", restore="both", split=None,
                   figures=0, out=tmp_path / "ev")
    got = {(s["preprocess"], s["restore"]): s["mrae"] for s in res.summary}
    assert set(got) == {("off", True), ("off", False), ("on", True)}
    assert all(v < 5 for v in got.values())
    notes = json.loads((tmp_path / "ev" / "evaluation.json").read_text())["config"]["notes"]
    assert any("linear" in n and "restoration off" in n and "inverse Reinhard" in n
               for n in notes)
    assert not any(n.endswith("scored under every requested setting") for n in notes)
    table = res.tables("text", metrics=("mrae",))
    assert "–" in table


def test_undeclared_model_asked_only_for_the_undefined_setting_is_refused(dataset, user):
    with pytest.raises(InputError, match="restoration off is undefined"):
        evaluate(dataset, [user], preprocess="on", restore=False, split=None, figures=0)


def test_fixed_baseline_keeps_its_inverse_reinhard_row(dataset):
    # Smits is declared (fixed): on tone-mapped RGB its output is tone-mapped, and the
    # inverse maps it back; that row stays
    res = evaluate(dataset, ["smits"], preprocess="on", restore=False, split=None, figures=0,
                   fixed_preprocess=True)
    assert [(s["preprocess"], s["restore"]) for s in res.summary] == [("on", False)]
    assert np.isfinite(res.summary[0]["mrae"])
