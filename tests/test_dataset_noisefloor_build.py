"""Ground-truth pixels buried in noise: mask bit 8, its count, and the scores it leaves.

A ColorChecker at 10⁻² of its light (deep shadows everywhere) is simulated, built into a
dataset and scored with Smits against the dataset's ``hs.hdr`` and against the simulator's
noise-free radiance resampled the same way. Before: MRAE 1.21 against ``hs.hdr``, 0.30
against the truth (48²); SAM 23.0° against 11.7°.
"""

import json

import cv2
import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene

TIMES = (0.04, 2.56, 163.84)


@pytest.fixture(scope="module")
def dim(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_dataset
    from mehs.rgb import WAVELENGTHS_31
    from mehs.synthesis.resample import resample_cube
    from mehs.synthesis.response import ResponseCurve

    root = tmp_path_factory.mktemp("noisefloor")
    sc = make_scene("colorchecker", 32, 32, seed=1)
    sc.radiance = sc.radiance * np.float32(1e-2)
    sc.white_radiance = sc.white_radiance * np.float32(1e-2)
    sim = simulate_bracket(sc, SensorModel(seed=3), TIMES)
    folder = write_simulated_scene(sim, root / "cc", overwrite=True)
    ResponseCurve.linear(12).save(root / "lin.json")
    m = build_dataset([folder], root / "ds", workers=1, progress=False,
                      response=root / "lin.json")
    entry = m["scenes"][0]
    truth = np.asarray(sim.truth, np.float32) * sim.truth_dn_per_ms.astype(np.float32)
    t31 = resample_cube(SpectralCube(truth, sim.wavelengths, fwhm=sim.fwhm),
                        WAVELENGTHS_31).data * np.float32(entry["quality"]["radiance_scale"])
    return root / "ds", entry, np.asarray(t31, np.float64)


def _smits(pair):
    from mehs.rgb import WAVELENGTHS_31
    from mehs.ssr.baselines import Smits1999
    from mehs.ssr.pipeline import predict

    return np.asarray(predict(Smits1999(), pair.hdr_rgb(), restore=True,
                              wavelengths=WAVELENGTHS_31), np.float64)


def test_unresolved_pixels_are_flagged_counted_and_recorded(dim):
    ds, entry, _ = dim
    q = entry["quality"]
    mask = cv2.imread(str(ds / entry["files"]["mask"]), cv2.IMREAD_UNCHANGED)
    unres = (mask & 8) > 0
    assert 0.2 < unres.mean() < 0.95                     # the dark patches, not the white
    assert q["noise_floor_fraction"] == pytest.approx(unres.mean())
    assert q["noise_floor_snr"] == 10.0
    nm = q["noise_model"]
    assert nm["format"] == "mehs-band-noise/1" and len(nm["zero"]) == 31
    # the other bits keep their meaning and their figures
    assert q["saturated_fraction"] == pytest.approx(np.mean(mask & 1 > 0))
    man = json.loads((ds / "manifest.json").read_text())
    assert man["quality_rules"]["max_noise_floor_fraction"] is None     # off by default


def test_noise_model_matches_the_simulator(dim):
    """σ of the recorded model against hs.hdr − truth, in the dark where it decides."""
    from mehs.dataset.noisefloor import sigma
    from mehs.io.envi import read_envi

    ds, entry, t31 = dim
    gt = np.asarray(read_envi(ds / entry["files"]["hs"]).data, np.float64)
    s = sigma(t31, entry["quality"]["noise_model"])
    dark = t31 < 20 * s                  # near the floor (no exposure saturates there)
    z = (gt - t31)[dark] / s[dark]
    assert dark.sum() > 5000
    assert 0.85 < z.std() < 1.2, z.std()


def test_scores_against_hs_track_the_noise_free_truth(dim):
    from mehs.ssr.data import load_pairs
    from mehs.ssr.metrics import image_metrics

    ds, entry, t31 = dim
    pair = load_pairs(ds)[0]
    gt, _ = pair.hs_array()
    pred = _smits(pair)
    valid = pair.valid(gt.shape[:2])
    floor = pair.mrae_floor(gt)
    assert pair.info["unresolved_pixels"] == int(np.count_nonzero(~valid))
    a = image_metrics(pred, gt, valid=valid, mrae_floor=floor)
    b = image_metrics(pred, t31, valid=valid, mrae_floor=floor)
    assert a["mrae"] == pytest.approx(b["mrae"], rel=0.1), (a["mrae"], b["mrae"])
    assert abs(a["sam"] - b["sam"]) < 1.0, (a["sam"], b["sam"])
    assert a["mrae_floor_excluded"] > 0
    # every pixel (the paper's protocol): the noise dominates
    full = load_pairs(ds, score_unresolved=True)[0]
    v_all = full.valid(gt.shape[:2])
    assert v_all.all() and full.mrae_floor(gt) is None
    c = image_metrics(pred, gt, valid=v_all)
    d = image_metrics(pred, t31, valid=v_all)
    assert c["mrae"] > 2.5 * d["mrae"] and c["sam"] > d["sam"] + 5


def test_a_mask_without_bit_8_reads_as_before(dim, tmp_path):
    """A dataset built before: no noise model, masks of bits 1/2/4 only."""
    import shutil

    from mehs.ssr.data import load_pairs

    ds, entry, _ = dim
    old = tmp_path / "old"
    shutil.copytree(ds, old)
    man = json.loads((old / "manifest.json").read_text())
    sc = man["scenes"][0]
    for k in ("noise_model", "noise_floor_fraction", "noise_floor_snr"):
        sc["quality"].pop(k)
    mpath = old / sc["files"]["mask"]
    mask = cv2.imread(str(mpath), cv2.IMREAD_UNCHANGED)
    mask = (mask & 7).astype(np.uint8)
    mask[0, 0] = 4
    cv2.imwrite(str(mpath), mask)
    (old / "manifest.json").write_text(json.dumps(man))
    pair = load_pairs(old, verify="none")[0]
    gt, _ = pair.hs_array()
    assert np.array_equal(pair.valid(gt.shape[:2]), mask == 0)
    assert pair.mrae_floor(gt) is None
    assert pair.info["unresolved_pixels"] == 0


def test_a_damaged_noise_model_is_named(dim, tmp_path):
    import shutil

    from mehs.errors import InputError
    from mehs.ssr.data import load_pairs

    ds, _, _ = dim
    bad = tmp_path / "bad"
    shutil.copytree(ds, bad)
    man = json.loads((bad / "manifest.json").read_text())
    man["scenes"][0]["quality"]["noise_model"]["zero"] = [1.0] * 30
    (bad / "manifest.json").write_text(json.dumps(man))
    pair = load_pairs(bad, verify="none")[0]
    gt, _ = pair.hs_array()
    with pytest.raises(InputError, match="hs.hdr.*31 finite values|31 finite values.*hs.hdr"):
        pair.mrae_floor(gt)


def test_mehs_evaluate_leaves_them_out_and_says_so_unless_asked(dim, tmp_path, capsys):
    # the command, not only the library: the rows count what was left out, the option
    # restores the paper's every-pixel protocol, and the two MRAEs differ as measured above
    from mehs.cli import main

    ds, entry, _ = dim
    n_unresolved = int(round(entry["quality"]["noise_floor_fraction"] * 32 * 32))
    runs = {}
    for flag in ([], ["--score-unresolved"]):
        out = tmp_path / ("all" if flag else "default")
        assert main(["evaluate", str(ds), "--models", "smits", "--out", str(out),
                     "--figures", "0", *flag]) == 0
        text = capsys.readouterr().out
        runs[bool(flag)] = (json.loads((out / "evaluation.json").read_text()), text)
    (res, text), (res_all, text_all) = runs[False], runs[True]
    row, row_all = res["rows"][0], res_all["rows"][0]
    assert row["unresolved_pixels"] == n_unresolved > 0
    assert row["n_pixels"] == 32 * 32 - n_unresolved and row["mrae_floor_excluded"] > 0
    assert "not resolved above its noise" in text and "--score-unresolved" in text
    assert row_all["n_pixels"] == 32 * 32 and row_all["unresolved_pixels"] is None
    assert "not resolved" not in text_all
    assert res_all["config"]["mrae_rule"]["score_unresolved"] is True
    assert row_all["mrae"] > 2 * row["mrae"]
    # the HTML report says what the table's scores leave out
    from mehs.ssr.report import write_evaluation_report

    html = write_evaluation_report(tmp_path / "default").read_text(encoding="utf-8")
    assert f"{n_unresolved} / {row['mrae_floor_excluded']}" in html
    assert "--score-unresolved" in html


def test_mehs_build_max_unresolved_fails_a_scene_too_dim(dim, tmp_path):
    # the build's rule is off by default (deep shadows are what HDR scenes are for);
    # --max-unresolved turns it on from the command line
    from mehs.cli import main

    ds, entry, _ = dim
    frac = entry["quality"]["noise_floor_fraction"]
    assert entry["status"] == "pass" and frac > 0.5
    out = tmp_path / "strict"
    folder = next(p for p in ds.parent.iterdir() if p.is_dir() and p.name == "cc")
    assert main(["build", str(folder), "--out", str(out), "--response",
                 str(ds.parent / "lin.json"), "--max-unresolved", "0.5", "--quiet",
                 "--workers", "1"]) in (0, 1)
    m = json.loads((out / "manifest.json").read_text())
    sc = m["scenes"][0]
    assert sc["status"] == "fail"
    assert any("unresolved" in r or "noise" in r for r in sc.get("reasons", [])), sc
