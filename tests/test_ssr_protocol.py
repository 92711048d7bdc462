"""The evaluation protocol: each model scored only in the setting it was trained for.

Every combination of a fixed baseline, pre-processing-trained and non-trained models (fitted
regressions and, with torch, networks incl. an end-to-end one) × HDR/LDR/both inputs ×
``--preprocess on|off|both`` evaluates and renders its report (issue 19's crash:
``KeyError: 'hdr-pp_off-lr_on-hdrssr'`` in the report).
"""

import itertools
import json
import re

import numpy as np
import pytest

from mehs.cli import main
from mehs.errors import InputError
from mehs.ssr.contract import TrainedFor
from mehs.ssr.preprocess import PAPER_PREPROCESSING, Preprocessing
from mehs.ssr.protocol import allowed
from mehs.ssr.synthetic import make_paired_set

#: A tiny network, in the keywords both the first release and the model zoo accept.
TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=8)


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return make_paired_set(tmp_path_factory.mktemp("proto") / "ds", n_scenes=4, size=16, seed=7)


@pytest.fixture(scope="module")
def models(ds, tmp_path_factory):
    """name → (spec, trained pre-processing on?, output kind)."""
    d = tmp_path_factory.mktemp("proto_models")
    out = {"smits": ("smits", None, "either")}
    for pp in ("on", "off"):
        path = d / f"reg_{pp}.npz"
        assert main(["train-baseline", str(ds), "--out", str(path), "--samples", "3000",
                     "--preprocess", pp]) == 0
        out[f"reg{pp}"] = (str(path), pp == "on", "either")
    try:
        import torch  # noqa: F401
    except ImportError:
        return out
    from mehs.ssr.net.model import build_network
    from mehs.ssr.net.train import TrainConfig, save_checkpoint

    torch.manual_seed(0)
    for name, variant, reinhard in (("netpp", "hdrssr", True), ("netraw", "hdrssr", False),
                                    ("e2e", "fcdensenet", True)):
        net = build_network(variant=variant, reinhard=reinhard, **TINY)
        path = d / f"{name}.pt"
        save_checkpoint(path, net, None, None, epoch=0, train_config=TrainConfig(), history=[])
        out[name] = (str(path), reinhard, "shape" if variant == "hdrssr" else "spectra")
    return out


def test_rules_from_declarations():
    fixed = TrainedFor(fixed=True)
    pp = TrainedFor(input="hdr", preprocessing=Preprocessing(), output="shape")
    e2e = TrainedFor(input="ldr", preprocessing=None, output="spectra")
    assert allowed(fixed, "hdr", "off", True) is None
    assert "unless asked" in allowed(fixed, "hdr", "on", True)
    assert allowed(fixed, "hdr", "on", True, fixed_preprocess=True) is None
    assert allowed(pp, "hdr", "on", True) is None and allowed(pp, "ldr", "on", True) is None
    assert "trained with reinhard key 0.18" in allowed(pp, "hdr", "off", True)
    assert "restoration" in allowed(pp, "hdr", "on", False)
    assert "end to end" in allowed(e2e, "ldr", "off", True)
    assert "LDR input only" in allowed(e2e, "hdr", "off", False)
    assert allowed(TrainedFor(declared=False), "hdr", "on", False) is None


def test_reinhard_key_is_unit_free_and_fixed_scale_is_not():
    rgb = np.random.default_rng(0).gamma(1.0, 1.0, (8, 8, 3)).astype(np.float32)
    key = Preprocessing()
    np.testing.assert_allclose(key(rgb * 300), key(rgb), rtol=1e-5)
    assert not np.allclose(PAPER_PREPROCESSING(rgb * 300), PAPER_PREPROCESSING(rgb))
    # Reinhard 2002: the log-average luminance lands on the key before x/(1+x)
    lum = rgb.reshape(-1, 3) @ np.array([0.2126, 0.7152, 0.0722])
    scaled = rgb * key.factor(rgb)
    assert np.exp(np.log(scaled.reshape(-1, 3) @ np.array([0.2126, 0.7152, 0.0722])).mean()) == \
        pytest.approx(0.18, rel=1e-5)
    assert lum.min() > 0
    assert Preprocessing.from_dict(key.to_dict()) == key
    assert Preprocessing.from_dict("reinhard") == PAPER_PREPROCESSING
    with pytest.raises(ValueError):
        Preprocessing(key=-1)


@pytest.mark.parametrize("inputs,pp", list(itertools.product(["hdr", "ldr", "hdr,ldr"],
                                                              ["on", "off", "both"])))
def test_every_combination_evaluates_and_reports(ds, models, tmp_path, inputs, pp, capsys):
    specs = ",".join(f"{n}={s}" for n, (s, _, _) in models.items())
    out = tmp_path / "res"
    rc = main(["evaluate", str(ds), "--models", specs, "--input", inputs, "--preprocess", pp,
               "--out", str(out), "--report", "--figures", "1", "--split", "all"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert (out / "report.html").is_file()
    if inputs == "hdr,ldr" and pp == "both":  # `mehs report` reads the same folder back
        assert main(["report", str(out), "--out", str(tmp_path / "again.html")]) == 0
    doc = json.loads((out / "evaluation.json").read_text())
    seen = {(r["model"], r["input"], r["preprocess"], r["restore"]) for r in doc["rows"]}
    want_pp = {"on": ["on"], "off": ["off"], "both": ["on", "off"]}[pp]
    for name, (_, trained_pp, kind) in models.items():
        mine = {s for s in seen if s[0] == name}
        expect_pp = ["off"] if trained_pp is None else ["on" if trained_pp else "off"]
        if not set(expect_pp) & set(want_pp):
            assert not mine, name                          # "–": never scored outside its setting
            continue
        assert {s[2] for s in mine} == set(expect_pp), name
        assert {s[1] for s in mine} == set(inputs.split(",")), name
        restores = {s[3] for s in mine}
        assert restores == {"shape": {True}, "spectra": {False}, "either": {True}}[kind], name
    md = (out / "tables.md").read_text()
    if pp == "both":
        # the paper's "–" in the tables: Smits has no pre-processing column value
        row = next(line for line in md.splitlines() if line.startswith("| smits |"))
        assert re.match(r"\| smits \| – \| – \| [\d.]+", row), row
    # fallbacks are counted for every restored configuration, never hidden
    for s in doc["summary"]:
        assert (s["restore_fallback"] is not None) == bool(s["restore"])


def test_issue_crash_command_and_named_rows(ds, models, tmp_path, capsys):
    if "netpp" not in models:
        pytest.skip("needs torch")
    ckpt = models["netpp"][0]
    out = tmp_path / "res"
    assert main(["evaluate", str(ds), "--models", f"smits,{ckpt}", "--preprocess", "both",
                 "--out", str(out), "--report"]) == 0
    assert main(["report", str(out)]) == 0
    doc = json.loads((out / "evaluation.json").read_text())
    assert {m["name"] for m in doc["models"]} == {"smits", "hdrssr"}
    out2 = tmp_path / "named"
    assert main(["evaluate", str(ds), "--models", f"ours={ckpt},mine={models['netraw'][0]},smits",
                 "--out", str(out2)]) == 0
    names = [m["name"] for m in json.loads((out2 / "evaluation.json").read_text())["models"]]
    assert names == ["ours", "mine", "smits"]
    capsys.readouterr()
    assert main(["evaluate", str(ds), "--models", f"a={ckpt},a={ckpt}", "--out",
                 str(tmp_path / "dup")]) == 2
    assert "named 'a' and were trained for the same setting" in capsys.readouterr().err


def test_nothing_trained_for_the_request_is_an_error(ds, tmp_path):
    from mehs.ssr.evaluate import evaluate

    with pytest.raises(InputError, match="no model was trained for the requested settings"):
        evaluate(ds, "smits,mallett", preprocess="on", split=None)
    res = evaluate(ds, "smits", preprocess="on", split=None, fixed_preprocess=True)
    assert {s["preprocess"] for s in res.summary} == {"on"}
    assert res.config["preprocessing"] == {"method": "reinhard", "key": 0.18, "scale": 1.0}


def test_end_to_end_is_not_restored_and_fallbacks_are_counted(ds):
    from mehs.ssr.contract import SSRModel
    from mehs.ssr.evaluate import evaluate

    class Negative(SSRModel):
        """A shape model whose output has X+Y+Z < 0 on every pixel: all fall back."""
        name = "neg"
        trained_for = TrainedFor(input="hdr", output="shape")

        def predict(self, rgb):
            return -np.ones((*rgb.shape[:2], 31), np.float32)

    class E2E(Negative):
        name = "e2e"
        trained_for = TrainedFor(input="hdr", output="spectra")

        def predict(self, rgb):
            return np.repeat(rgb[..., 1:2], 31, -1)

    res = evaluate(ds, [Negative(), E2E()], preprocess="off", split=None, restore=True)
    by = {(s["model"], s["restore"]): s for s in res.summary}
    assert set(by) == {("neg", True), ("e2e", False)}
    neg = by[("neg", True)]
    n_lit = neg["restore_fallback"]
    assert n_lit > 0 and neg["restore_fallback_fraction"] > 0.9
    assert any("fell back to a flat spectrum" in n and n.startswith("neg") for n in res.config["notes"])
    # e2e output used as is: its value is the green channel in every band
    assert by[("e2e", False)]["restore_fallback"] is None
    # with a border crop the fallbacks are counted in the scored region too: a fraction
    # of the pixels scored, never above 1 (they were counted over the whole image)
    cropped = evaluate(ds, [Negative()], preprocess="off", split=None, restore=True, crop=3)
    c = cropped.summary[0]
    assert 0.9 < c["restore_fallback_fraction"] <= 1.0
    assert c["restore_fallback"] < n_lit


def test_mrae_rule_and_pixels_are_recorded(ds, tmp_path):
    from mehs.ssr.data import load_pairs
    from mehs.ssr.evaluate import evaluate

    scene = load_pairs(ds)[0].id
    res = evaluate(ds, "smits", preprocess="off", split=None, out=tmp_path / "r", figures=0,
                   pixels=[f"{scene}:3,4"], mrae_threshold=0.05, mrae_relative=True,
                   mrae_bands=(450, 650))
    base = evaluate(ds, "smits", preprocess="off", split=None)
    assert res.config["mrae_rule"] == {"threshold": 0.05, "relative": True,
                                       "band_range": [450.0, 650.0], "score_unresolved": False}
    assert res.summary[0]["mrae"] != base.summary[0]["mrae"]
    assert res.summary[0]["mrae_excluded"] > base.summary[0]["mrae_excluded"]
    assert res.figures == [scene]                 # kept for the chosen pixel although figures=0
    with np.load(tmp_path / "r" / "figures" / f"{scene}.npz") as z:
        assert z["pixels"][0].tolist() == [3, 4] and int(z["n_user_pixels"]) == 1
    with pytest.raises(InputError, match="SCENE:ROW,COL"):
        evaluate(ds, "smits", preprocess="off", pixels=["oops"])
    with pytest.raises(InputError, match="not among the scored scenes"):
        evaluate(ds, "smits", preprocess="off", split=None, pixels=["nope:1,1"])


def test_a_column_where_every_model_ties_marks_no_best():
    from mehs.ssr.results_io import best_marks, per_scene_blocks

    # PSNR at its 120 dB cap for the two models scored: no "best"; SAM still marked
    assert best_marks([[1.0, 120.0], [2.0, 120.0], [None, None]], ["sam", "psnr"]) == \
        [[True, False], [False, False], [False, False]]
    assert best_marks([[1.0004], [1.0001]], ["sam"]) == [[False], [False]]   # tie as shown
    assert best_marks([[1.0]], ["sam"]) == [[True]]                           # alone is best
    rows = [{"scene": sc, "input": "hdr", "preprocess": "off", "restore": True, "model": m,
             "sam": v} for sc, m, v in (("a", "x", 1.0), ("a", "y", 2.0), ("b", "x", 3.0),
                                       ("b", "y", 3.0))]
    assert per_scene_blocks(rows, [])[0][3] == [[True, False], [False, False]]
