"""Synthesis: response recovery, merging, ghosts, bracket loading, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.synthesis.bracket import Bracket, load_bracket
from mehs.synthesis.fuse import fuse_bracket, recover_response, write_fusion
from mehs.synthesis.merge import MERGE_METHODS, merge_bracket
from mehs.synthesis.response import (ResponseCurve, recover_response_Debevec1997,
                                     sample_pixels, to_levels)


# ------------------------------------------------------------------ helpers
def _simulated(response="gamma", lines=96, samples=96, bands=None, times=(8.0, 32.0, 128.0),
               motion=False, e_per_ms=1600.0, seed=3):
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket

    wl = SPECIM_IQ_WAVELENGTHS if bands is None else SPECIM_IQ_WAVELENGTHS[::bands]
    sc = make_scene("colorchecker", lines=lines, samples=samples, wavelengths=wl,
                    source_ratio=300, motion=motion, seed=1)
    sen = SensorModel(response=response, seed=2, radiance_to_e_per_ms=e_per_ms)
    sim = simulate_bracket(sc, sen, list(times), seed=seed)
    br = Bracket([SpectralCube(e, sc.wavelengths) for e in sim.exposures], list(sim.darks),
                 [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12,
                 metadata={"device": {"sensor": {"gain_dn_per_e": sen.gain_dn_per_e,
                                                 "read_noise_e": sen.read_noise_e}}})
    return sim, br, sen


def _scores(rad, truth, ok):
    """Median / p99 relative error (after one global scale: the curve's gauge) and median SAM°."""
    s = np.median((rad / truth)[ok])
    rel = np.abs(rad / s - truth) / truth
    cos = np.einsum("ijk,ijk->ij", rad, truth) / (np.linalg.norm(rad, axis=2)
                                                  * np.linalg.norm(truth, axis=2))
    sam = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return float(np.median(rel[ok])), float(np.percentile(rel[ok], 99)), float(np.median(sam[ok]))


def _opencv_debevec(stack_levels, times, response_lin):
    """OpenCV MergeDebevec three bands at a time, with our curve as its response LUT."""
    import cv2

    P = len(stack_levels)
    nl, ns, nb = stack_levels[0].shape
    merge = cv2.createMergeDebevec()
    out = np.zeros((nl, ns, nb), np.float32)
    lut = np.ones((65536, 1, 3), np.float32)
    for b0 in range(0, nb, 3):
        idx = [min(b, nb - 1) for b in range(b0, b0 + 3)]
        for k, b in enumerate(idx):
            lut[:4096, 0, k] = response_lin if response_lin.ndim == 1 else response_lin[b]
        imgs = [np.ascontiguousarray(s[:, :, idx]).astype(np.uint16) for s in stack_levels]
        r = merge.process(imgs, np.asarray(times, np.float32), lut)
        for k, b in enumerate(idx):
            out[:, :, b] = r[:, :, k]
    return out


# ------------------------------------------------------------ response curves
def test_recovered_curve_matches_true_nonlinear_response():
    sim, br, sen = _simulated("gamma", bands=8)
    curve = recover_response(br, levels="raw", shared=False, seed=0)
    z = np.arange(4096)
    true = sen.true_log_inverse_response(z)
    # Debevec's model has no offset, so the black level (32 DN + dark current, added
    # before the non-linearity) bends the low end: compare over the well-exposed levels
    sel = (z > 800) & (z < 3900)
    d = curve.table()[:, sel] - true[sel]
    d -= np.median(d, axis=1, keepdims=True)     # the gauge: one constant per curve
    assert np.median(np.abs(d)) < 0.02
    assert np.percentile(np.abs(d), 95) < 0.06
    # and it is clearly not the linear curve: ln z is off by far more
    dl = np.log(z[sel]) - true[sel]
    dl -= np.median(dl)
    assert np.abs(dl).max() > 0.2


def test_pcg_equals_direct_solve_and_is_deterministic():
    rng = np.random.default_rng(0)
    E = np.exp(rng.uniform(np.log(20), np.log(400), (6000, 2)))
    t = np.array([1.0, 3.0, 9.0])
    raw = np.clip(np.rint(4095 * (np.clip(E[None] * t[:, None, None], 0, None) / 4095) ** 0.7
                          + rng.normal(0, 1.5, (3, 6000, 2))), 0, 4095)
    lev = to_levels(raw, None, 12, 4095)
    Z = sample_pixels(lev, 2900, seed=1, bit_depth=12)
    assert Z.shape == (2900, 3, 2)
    np.testing.assert_array_equal(Z, sample_pixels(lev, 2900, seed=1, bit_depth=12))
    a = recover_response_Debevec1997(Z, np.log(t), bit_depth=12, solver="pcg")
    b = recover_response_Debevec1997(Z, np.log(t), bit_depth=12, solver="direct")
    assert a.g.shape == (2, 4096)
    np.testing.assert_allclose(a.g, b.g, atol=1e-6)
    assert a.g[0, 2048] == pytest.approx(np.log(2048))        # the gauge


def test_curve_save_load_roundtrip(tmp_path):
    g = np.log(np.maximum(np.arange(256), 0.5)) * 1.1
    c = ResponseCurve(np.stack([g, g + 0.1]), 8, smoothness=10.0, wavelengths=[500, 600],
                      parameters={"seed": 3})
    p = c.save(tmp_path / "curve.json")
    d = ResponseCurve.load(p)
    np.testing.assert_array_equal(d.g, c.g)
    assert d.bit_depth == 8 and d.parameters["seed"] == 3 and not d.shared
    np.testing.assert_allclose(d.log_exposure(np.array([[10, 20]])), [[g[10], g[20] + 0.1]])
    (tmp_path / "bad.json").write_text('{"format": "other"}')
    with pytest.raises(FormatError, match="bad.json"):
        ResponseCurve.load(tmp_path / "bad.json")


def test_8bit_ldr_curve_correlates_with_opencv():
    """An 8-bit, 3-channel stack from a radiance map with a known ladder (gamma 2.2 camera)."""
    import cv2

    rng = np.random.default_rng(5)
    hdr = np.exp(rng.uniform(np.log(0.002), np.log(2.0), (64, 64, 3))).astype(np.float32)
    times = np.array([1 / 8, 1 / 2, 2.0, 8.0], np.float32)
    stack = [np.clip(255 * np.clip(hdr * t + rng.normal(0, 0.002, hdr.shape), 0, 1) ** (1 / 2.2),
                     0, 255).round().astype(np.uint8) for t in times]
    lev = np.stack([s.reshape(-1, 3) for s in stack]).astype(np.int32)
    lev[lev >= 255] = 255
    Z = sample_pixels(lev, 200, seed=0, bit_depth=8)
    ours = recover_response_Debevec1997(Z, np.log(times), bit_depth=8, smoothness=10.0)
    cv = np.log(cv2.createCalibrateDebevec(samples=200, random=False).process(
        stack, times)[:, 0, :]).T                                      # (3, 256)
    z = np.arange(50, 236)
    for c in range(3):
        r = np.corrcoef(ours.g[c, z], cv[c, z])[0, 1]
        assert r > 0.99, (c, r)
    true = 2.2 * np.log(z / 255.0)
    d = ours.g[:, z] - true
    d -= d.mean(axis=1, keepdims=True)
    assert np.abs(d).max() < 0.1, np.abs(d).max(axis=1)   # OpenCV: 0.05 here


# ------------------------------------------------------------------ merging
def test_merge_accuracy_beats_opencv_on_nonlinear_bracket():
    sim, br, sen = _simulated("gamma", bands=2)
    res = fuse_bracket(br, method="inverse-variance", response="auto", ghosts="off")
    assert res.response.method == "debevec1997"        # auto saw the non-linearity
    truth = sim.truth * sim.truth_dn_per_ms
    ok = (sim.exposures[0] < 0.98 * 4095).all(axis=2)
    med, p99, sam = _scores(res.radiance.data, truth, ok)
    assert med <= 0.03 and p99 <= 0.5 and sam <= 1.0, (med, p99, sam)
    # OpenCV MergeDebevec on the same stack (dark-subtracted levels), 3 bands a call,
    # given a Debevec curve we recovered on those levels (OpenCV's CalibrateDebevec is 8-bit only)
    curve = recover_response(br, levels="dark-subtracted", shared=True)
    levs = [to_levels(e.data, d, 12, 0.98 * 4095) for e, d in zip(br.exposures, br.darks)]
    cv = _opencv_debevec(levs, br.times_ms, np.exp(curve.g).astype(np.float32))
    cmed, cp99, csam = _scores(cv, truth, ok & np.all(cv > 0, axis=2))
    assert med < cmed and p99 < cp99 and sam < csam, ((med, p99, sam), (cmed, cp99, csam))


@pytest.mark.parametrize("method", sorted(MERGE_METHODS))
def test_linear_methods_unbiased_and_flag_saturation(method):
    rng = np.random.default_rng(1)
    E = np.exp(rng.uniform(np.log(5), np.log(300), (40, 30, 1))) * np.linspace(0.5, 1, 6)
    E[0, 0] = 5000.0                              # saturated in every exposure
    t = [16.0, 1.0, 4.0]                          # unsorted on purpose
    dark = np.full((30, 6), 50.0, np.float32)
    stack = [np.clip(np.rint(rng.poisson(E * tt) + rng.normal(0, 2, E.shape) + 50), 0, 4095)
             .astype(np.uint16) for tt in t]
    r = merge_bracket(stack, t, method=method, darks=[dark] * 3)
    assert r.radiance.dtype == np.float32 and np.all(np.isfinite(r.radiance))
    assert r.mask[0, 0] & 1 and not r.mask[1:, 1:].any()
    # a lower bound, not an invented value
    assert np.all(r.radiance[0, 0] <= (4095 - 50) / 1.0 + 1)
    good = np.ones(E.shape[:2], bool)
    good[0, 0] = False
    rel = (r.radiance - E)[good] / E[good]
    assert abs(np.median(rel)) < 0.01
    assert np.median(np.abs(rel)) < 0.03
    assert r.confidence[good].min() > 1


def test_chunking_and_bil_layout_give_identical_results():
    rng = np.random.default_rng(2)
    E = rng.uniform(1, 200, (20, 16, 5))
    stack = [np.clip(np.rint(E * t + 20), 0, 4095).astype(np.uint16) for t in (1, 4, 16)]
    a = merge_bracket(stack, [1, 4, 16], chunk_lines=20)
    bil = [np.ascontiguousarray(s.transpose(0, 2, 1)).transpose(0, 2, 1) for s in stack]
    b = merge_bracket(bil, [1, 4, 16], chunk_lines=3)
    np.testing.assert_array_equal(a.radiance, b.radiance)
    np.testing.assert_array_equal(a.chi2, b.chi2)


# -------------------------------------------------------------------- ghosts
def test_ghost_mask_finds_moving_patch_and_deghost_has_single_edge():
    sim, br, sen = _simulated("linear", lines=64, samples=64, bands=6, motion=True)
    moved = sim.scene.moved_mask(3)
    res = fuse_bracket(br, response="linear", ghosts="deghost", ghost_alpha=1e-4)
    ghost = (res.mask & 2) > 0
    tp = np.sum(ghost & moved)
    precision = tp / max(ghost.sum(), 1)
    recall = tp / moved.sum()
    print(f"ghost precision {precision:.3f} recall {recall:.3f}")
    assert precision >= 0.7 and recall >= 0.8, (precision, recall)
    # de-ghosted: the region equals ONE exposure's scene (the reference), not a blend
    ref = res.summary["ghost_reference_exposure"]
    assert ref is not None
    truth_ref = sim.scene.radiance_at(ref) * sim.truth_dn_per_ms
    blend = fuse_bracket(br, response="linear", ghosts="detect").radiance.data
    inside = ghost & moved & ((res.mask & 1) == 0)
    err_de = np.median(np.abs(res.radiance.data[inside] - truth_ref[inside]) / truth_ref[inside])
    err_bl = np.median(np.abs(blend[inside] - truth_ref[inside]) / truth_ref[inside])
    assert err_de < 0.1 and err_de < 0.5 * err_bl, (err_de, err_bl)
    # no double edge: along the motion direction the de-ghosted row profile
    # rises and falls once, like the reference frame's
    row = int(np.argmax(moved.sum(axis=1)))
    prof = res.radiance.data[row].mean(axis=1)
    tprof = truth_ref[row].mean(axis=1)
    peaks = lambda p: int(np.sum((p[1:-1] > p[:-2]) & (p[1:-1] >= p[2:])
                                 & (p[1:-1] > 1.5 * np.median(p))))
    assert peaks(prof) == peaks(tprof)


def test_static_scene_has_few_ghosts():
    sim, br, sen = _simulated("linear", lines=48, samples=48, bands=6)
    res = fuse_bracket(br, response="linear", ghosts="detect")
    assert res.summary["ghost_fraction"] < 0.01


def test_ghost_fraction_is_unknown_when_not_tested():
    # 0.0 would read as "tested, none moved" and pass a dataset's ghost rule
    sim, br, sen = _simulated("linear", lines=16, samples=16, bands=4, motion=True)
    res = fuse_bracket(br, response="linear", ghosts="off")
    assert res.summary["ghost_fraction"] is None


# --------------------------------------------------------- bracket / fuse I/O
def test_scene_folder_roundtrip_fuse_and_write(tmp_path):
    from mehs.capture.simulate import write_simulated_scene
    from mehs.io.envi import read_envi

    sim, br, sen = _simulated("linear", lines=24, samples=20, bands=12)
    scene = write_simulated_scene(sim, tmp_path / "scene1")
    b = load_bracket(scene)
    assert b.truth is not None and len(b.exposures) == 3
    np.testing.assert_array_equal(b.times_ms, sim.times_ms)
    res = fuse_bracket(b, response="linear")
    paths = write_fusion(res, tmp_path / "out")
    cube = read_envi(paths["radiance"])
    np.testing.assert_array_equal(np.asarray(cube.data), res.radiance.data)
    np.testing.assert_allclose(cube.wavelengths, sim.wavelengths, atol=1e-3)
    s = json.loads(paths["summary"].read_text())
    assert s["exposure_ratios"] == [1.0, 4.0, 16.0] and s["dynamic_range_stops"] > 4
    assert ResponseCurve.load(paths["response"]).is_linear
    # a corrupted raw file is caught by the SHA-256 check
    raw = next((scene / "exposures").glob("1_*/capture/*.raw"))
    data = bytearray(raw.read_bytes())
    data[100] ^= 0xFF
    raw.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="SHA-256"):
        load_bracket(scene)


def test_cli_fuse(tmp_path, capsys):
    from mehs.capture.simulate import write_simulated_scene
    from mehs.cli import main

    sim, br, sen = _simulated("linear", lines=20, samples=16, bands=17)
    scene = write_simulated_scene(sim, tmp_path / "s")
    rc = main(["fuse", str(scene), "--out", str(tmp_path / "o"), "--response", "linear",
               "--method", "robertson", "--ghosts", "off", "--calibration", "2"])
    assert rc == 0
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert s["method"] == "robertson" and s["units"] == "radiance"
    assert main(["fuse", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")]) == 2
    assert "nothing" in capsys.readouterr().err


# ----------------------------------------------------------------- bad input
def _cube(v=0, shape=(4, 5, 3), wl=(500, 600, 700), dtype=np.uint16):
    return SpectralCube(np.full(shape, v, dtype), wl)


@pytest.mark.parametrize("times, msg", [
    ([1.0, 1.0], "distinct"), ([0.0, 2.0], "positive"), ([-1.0, 2.0], "positive"),
    ([1.0], "at least 2"), ([1.0, np.nan], "positive")])
def test_bad_times(times, msg):
    exps = [_cube(100) for _ in times]
    with pytest.raises(InputError, match=msg):
        Bracket(exps, [None] * len(times), [None] * len(times), np.array(times),
                exps[0].wavelengths, source="scene_x")
    if len(times) >= 2:
        with pytest.raises(InputError, match=msg):
            merge_bracket([e.data for e in exps], times)


def test_bad_shapes_wavelengths_nan_and_all_saturated():
    with pytest.raises(InputError, match="shapes differ"):
        Bracket([_cube(), _cube(shape=(4, 6, 3))], [None] * 2, [None] * 2, np.array([1., 2.]),
                np.array([500., 600., 700.]), source="s")
    with pytest.raises(InputError, match="wavelengths differ"):
        Bracket([_cube(), _cube(wl=(500, 600, 701))], [None] * 2, [None] * 2,
                np.array([1., 2.]), np.array([500., 600., 700.]), source="s")
    nan = _cube(dtype=np.float32)
    nan.data[1, 1, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        Bracket([_cube(dtype=np.float32), nan], [None] * 2, [None] * 2, np.array([1., 2.]),
                np.array([500., 600., 700.]), source="s")
    with pytest.raises(InputError, match="saturated in every exposure"):
        merge_bracket([np.full((4, 5, 3), 4095, np.uint16)] * 2, [1.0, 2.0], source="sceneZ")
    with pytest.raises(InputError, match="sceneZ"):
        merge_bracket([np.full((4, 5, 3), 4095, np.uint16)] * 2, [1.0, 2.0], source="sceneZ")


def test_underdetermined_response_and_bad_levels():
    with pytest.raises(InputError, match="do not exceed"):
        sample_pixels(np.ones((3, 100), np.int32) * 5, 1000, bit_depth=12)
    with pytest.raises(InputError, match="levels must lie"):
        recover_response_Debevec1997(np.full((300, 2), 300), np.log([1, 2]), bit_depth=8)
    with pytest.raises(InputError, match="distinct"):
        recover_response_Debevec1997(np.full((300, 2), 3), np.log([2, 2]), bit_depth=8)


def test_load_bracket_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_bracket(tmp_path / "missing")
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "scene.json").write_text(json.dumps(
        {"format": "mehs-scene/1", "exposures": [{"status": "incomplete"}]}))
    with pytest.raises(InputError, match="complete exposure"):
        load_bracket(tmp_path / "s")


def test_auto_response_picks_linear_for_linear_sensor_and_specim_folder_list(tmp_path):
    from mehs.capture.simulate import write_simulated_scene

    sim, br, sen = _simulated("linear", lines=64, samples=64, bands=17)
    res = fuse_bracket(br, response="auto", ghosts="off")
    assert res.response.is_linear, res.summary["response"]
    assert res.summary["response"]["linearity_deviation"] < 0.02
    # the same exposures given as Specim IQ folders (times from each header's tint), unsorted
    scene = write_simulated_scene(sim, tmp_path / "s")
    folders = sorted((scene / "exposures").iterdir(), reverse=True)
    b = load_bracket(folders)
    np.testing.assert_allclose(b.times_ms, sim.times_ms)
    from mehs.synthesis.merge import NoiseModel

    nm = NoiseModel(gain=0.25, read_noise=2.1, relative=0.0)
    r2 = fuse_bracket(b, response="linear", ghosts="off", noise=nm)
    r1 = fuse_bracket(br, response="linear", ghosts="off", noise=nm)
    # darks are stored rounded to whole DN in the folders: agreement to that level,
    # except where the rounding tips a sample over the "3σ below saturation" rule
    diff = np.abs(r2.radiance.data - r1.radiance.data)
    assert np.mean(diff <= 0.5 / 8 + 1e-4) > 0.999
    assert np.all(diff <= 0.02 * np.abs(r1.radiance.data) + 0.5 / 8 + 1e-4)


def test_per_band_curve_of_other_wavelengths_is_refused(tmp_path):
    from mehs.errors import InputError
    from mehs.synthesis.response import ResponseCurve

    sim, br, sen = _simulated("linear", lines=12, samples=12, bands=17)
    nb = br.wavelengths.size
    ok = ResponseCurve.linear(12, bands=nb, wavelengths=br.wavelengths)
    fuse_bracket(br, response=ResponseCurve.load(ok.save(tmp_path / "ok.json")), ghosts="off")
    # the same band count, centres 3 nm off (another binning offset): each band would be
    # linearised with a neighbour's curve
    other = ResponseCurve.linear(12, bands=nb, wavelengths=br.wavelengths + 3.0)
    with pytest.raises(InputError, match="other wavelengths"):
        fuse_bracket(br, response=ResponseCurve.load(other.save(tmp_path / "o.json")), ghosts="off")
