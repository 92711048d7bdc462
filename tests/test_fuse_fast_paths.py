"""The shortcuts that keep `mehs fuse` fast (issue 16) give what they replace."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mehs.errors import FormatError

ROOT = Path(__file__).resolve().parents[1]


def _groups_of(x, bad, groups):
    """Each value's group, from mehs's cell table over the cells in use."""
    from mehs.synthesis._ptc_groups import _cell_groups
    from _ptc_reference import cells_of

    c = cells_of(x)
    if bad.all():
        return None
    lo, table = _cell_groups(c[~bad], groups)
    # (cells beyond the good ones' span take the nearest end, as in the compiled pass)
    return table[np.clip(c - lo, 0, table.size - 1)].astype(np.intp)


def test_instrument_groups_are_ordered_ranges_of_equal_size():
    rng = np.random.default_rng(1)
    n = 200000
    for x in (rng.gamma(0.5, 800, n).astype(np.float32),                   # continuous
              np.round(rng.gamma(0.3, 30, n) - 3).astype(np.float32)):    # dark: integer ties
        bad = rng.random(n) < 0.02
        g = _groups_of(x, bad, 48)
        assert g.min() >= 0 and g.max() <= 47
        # ranges of the instrument: a group's values all lie below the next group's
        hi = np.full(48, -np.inf)
        lo = np.full(48, np.inf)
        np.maximum.at(hi, g, x)
        np.minimum.at(lo, g, x)
        used = np.flatnonzero(np.bincount(g, minlength=48))
        assert np.all(hi[used[:-1]] < lo[used[1:]])
        # tied values (one cell) share a group
        for v in np.unique(x)[:20]:
            assert np.unique(g[x == v]).size == 1
    # continuous data: good samples split evenly (one cell, ≤ 0.1 % of the value, of slack per edge)
    x = rng.normal(1000, 300, n).astype(np.float32)
    bad = np.zeros(n, bool)
    sizes = np.bincount(_groups_of(x, bad, 48), minlength=48)
    assert np.all(np.abs(sizes / (n / 48) - 1) < 0.1), sizes
    assert _groups_of(x, np.ones(n, bool), 48) is None


def test_16bit_roughness_equals_float_medians():
    from mehs.io.plausibility import _roughness

    def reference(x):
        x = x.astype(np.float64)
        d = float(np.median(np.abs(np.diff(x, axis=-1))))
        s = float(np.median(np.abs(x - np.median(x))))
        return d / s if s > 0 else 0.0

    rng = np.random.default_rng(0)
    for k in range(60):
        shape = (int(rng.integers(1, 4)), int(rng.integers(1, 30)), int(rng.integers(2, 25)))
        x = [rng.integers(0, 4096, shape).astype(np.uint16),
             rng.integers(0, 4096, shape).astype(np.uint16).byteswap(),
             rng.integers(-300, 300, shape).astype(np.int16),
             np.full(shape, 7, np.uint16)][k % 4]
        assert _roughness(x) == reference(x)


def _scene(tmp_path):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    sim = simulate_bracket(make_scene("window", 24, 24, seed=1), SensorModel(seed=3),
                           (0.05, 0.4, 3.2), seed=0)
    return write_simulated_scene(sim, tmp_path / "scene", scene_id="s")


def test_deferred_check_stops_the_fusion_of_an_altered_raw(tmp_path):
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket

    scene = _scene(tmp_path)
    fuse_bracket(load_bracket(scene, defer_verify=True), ghosts="off")   # intact: fine
    raw = next((scene / "exposures").glob("1_*/capture/*.raw"))
    data = bytearray(raw.read_bytes())
    data[100] ^= 0xFF
    raw.write_bytes(bytes(data))
    br = load_bracket(scene, defer_verify=True)      # returns while hashing
    with pytest.raises(FormatError, match="SHA-256") as exc:
        fuse_bracket(br, ghosts="off")
    assert raw.name in str(exc.value)
    with pytest.raises(FormatError, match="SHA-256"):
        load_bracket(scene)                          # not deferred: raised right away


def test_fuse_loads_no_scipy_linalg_stats_or_optional_packages(tmp_path):
    """numba starts without scipy.linalg, and neither scipy.stats nor anything optional
    (colour, matplotlib, torch, dask, onnxruntime) is imported."""
    scene = _scene(tmp_path)
    code = ("import sys\nfrom mehs.cli import main\n"
            f"rc = main(['fuse', {str(scene)!r}, '--out', {str(tmp_path / 'out')!r}])\n"
            "mods = ('scipy.linalg', 'scipy.stats', 'scipy.special', 'scipy.ndimage', 'colour',\n"
            "        'matplotlib', 'torch', 'dask', 'onnxruntime')\n"
            "print('LOADED', [m for m in mods if m in sys.modules], rc)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "LOADED [] 0" in r.stdout, r.stdout + r.stderr[-2000:]


@pytest.mark.parametrize("method", ["poisson", "debevec"])
def test_warm_merge_kernel_prepares_the_very_specialisation_the_merge_uses(method):
    """The first line of the stack gives the whole stack's kernel signature, read-only
    BIL memory maps included: the merge after it compiles nothing new. (int16 raws: a
    type no other test merges, so the signature cannot come from another test.)"""
    from mehs.synthesis import _merge_fused as F
    from mehs.synthesis import _merge_fused_weighted as W
    from mehs.synthesis.merge import merge_bracket, warm_merge_kernel

    rng = np.random.default_rng(0)
    stack = []
    for t in (1.0, 4.0, 16.0):
        bil = np.ascontiguousarray(np.clip(rng.normal(300 * t, 20, (6, 7, 9)), 0, 4095)
                                   .astype(np.int16))        # (lines, bands, samples) on disk
        bil.flags.writeable = False
        stack.append(bil.transpose(0, 2, 1))                 # (lines, samples, bands) view
    darks = [np.full((9, 7), 10.0)] * 3
    warm_merge_kernel(stack, [1.0, 4.0, 16.0], method=method, darks=darks).join(600)
    # (a linear sensor's merges: the one-pass kernels)
    kernel = (F.merge_chunk_poisson_linear if method == "poisson"
              else W.merge_chunk_debevec_linear)

    def mine():     # (a warm-up thread of another test may add uint16 signatures meanwhile)
        return {sig for sig in kernel.signatures if "array(int16," in str(sig[0])}

    before = mine()
    assert before
    merge_bracket(stack, [1.0, 4.0, 16.0], method=method, darks=darks)
    assert mine() == before


def test_warm_merge_kernel_for_a_recovered_curve_prepares_the_stage_kernel():
    """A recovered (non-linear) curve's Poisson merge runs the stage kernel: warming with
    ``linear=False`` loads the very specialisation a merge with any such curve uses."""
    from mehs.synthesis import _merge_kernels as K
    from mehs.synthesis.merge import merge_bracket, warm_merge_kernel
    from mehs.synthesis.response import ResponseCurve

    rng = np.random.default_rng(1)
    stack = []
    for t in (1.0, 4.0, 16.0):
        bil = np.ascontiguousarray(np.clip(rng.normal(300 * t, 20, (5, 6, 8)), 0, 4095)
                                   .astype(np.int32))        # a type no other test merges
        bil.flags.writeable = False
        stack.append(bil.transpose(0, 2, 1))
    darks = [np.full((8, 6), 10.0)] * 3
    warm_merge_kernel(stack, [1.0, 4.0, 16.0], darks=darks, linear=False).join(600)
    def mine():
        return {sig for sig in K.merge_chunk_poisson.signatures if "array(int32," in str(sig[0])}

    before = mine()
    assert before
    g = np.log(np.maximum(np.arange(4096.0), 0.5))[None].repeat(6, 0) * 1.02   # per band
    curve = ResponseCurve(g, 12, "debevec1997", parameters={"levels": "raw"})
    merge_bracket(stack, [1.0, 4.0, 16.0], darks=darks, response=curve)
    assert mine() == before


def test_a_warm_fuse_starts_no_numba(tmp_path):
    """With the kernels stored in the mehs cache, ``mehs fuse`` loads their machine code
    (the merge's and the photon-transfer pass and subset) without importing numba; a first
    run stores them, compiling the photon-transfer kernels in child processes."""
    scene = _scene(tmp_path)
    code = ("import sys\n"
            "from mehs.synthesis.bracket import load_bracket\n"
            "from mehs.synthesis.fuse import fuse_bracket\n"
            "r = fuse_bracket(load_bracket(sys.argv[1]))\n"
            "print('NUMBA', 'numba' in sys.modules, 'NOISE', r.summary['noise']['source'])\n")
    env = dict(os.environ, MEHS_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(ROOT))
    folder = tmp_path / "cache" / "kernels"

    def run():
        r = subprocess.run([sys.executable, "-c", code, str(scene)], capture_output=True,
                           text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        return r

    runs = [run()]
    # the first run used numpy's passes and left the child to finish storing them
    deadline = time.monotonic() + 600
    while (not (list(folder.glob("ptc_pass-*.json")) and list(folder.glob("ptc_subset-*.json")))
           and time.monotonic() < deadline):
        time.sleep(0.2)
    runs.append(run())
    kernels = sorted(p.name.split("-")[0] for p in folder.glob("*.o"))
    # (a dense spectrum: the default merge's χ² of bins of bands)
    assert kernels == ["poisson_linear_binned", "ptc_pass", "ptc_subset"]
    assert "NUMBA False" in runs[1].stdout, runs[1].stdout + runs[1].stderr
    assert "photon transfer" in runs[1].stdout          # the statistics ran, natively


def test_cell_groups_from_sorted_cells_equal_the_counted_table():
    """(session 30) the table from the sorted cells is the reference's counted one, ties
    and all"""
    from _ptc_reference import group_of_cells

    from mehs.synthesis._ptc_groups import _cell_groups

    rng = np.random.default_rng(7)
    cases = [rng.integers(-70000, 70000, 40000), rng.integers(5, 9, 3000),
             np.full(17, 123), rng.integers(0, 3, 5), np.array([4]),
             np.concatenate([rng.integers(-50, 50, 1000), np.full(5000, 7)])]
    cases += [rng.integers(-2 ** rng.integers(1, 17), 2 ** 17, rng.integers(1, 5000))
              for _ in range(200)]
    for cells in cases:
        cells = cells.astype(np.int32)
        for groups in (1, 2, 7, 48):
            lo, table = _cell_groups(cells, groups)
            ref_lo, ncells, ends = group_of_cells(cells, groups)
            assert lo == ref_lo
            # (the reference: cell lo + r is in group #(ends <= r))
            np.testing.assert_array_equal(
                table, np.searchsorted(ends, np.arange(ncells), side="right"))
