"""Start-up cost of the CLI paths (issue 16): light imports, same numbers."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("n", [1, 9, 10, 11, 97, 4096, 10001])
@pytest.mark.parametrize("cut", [0.0, 0.1, 0.25])
def test_trim_mean_equals_scipy(n, cut):
    from scipy.stats import trim_mean

    from mehs.synthesis.noise import _trim_mean

    a = np.round(np.random.default_rng(n).normal(3, 5, n))   # many ties, like rounded darks
    assert _trim_mean(a, cut) == pytest.approx(trim_mean(a, cut), rel=1e-12, abs=1e-12)


def test_chi2_quantiles_equal_scipy_stats():
    from scipy import stats
    from scipy.special import chdtri

    dof = np.arange(1, 800)
    np.testing.assert_allclose(chdtri(dof, 0.5), stats.chi2.median(dof), rtol=1e-12)
    np.testing.assert_allclose(chdtri(dof, 1e-4), stats.chi2.isf(1e-4, dof), rtol=1e-12)


def test_fuse_imports_no_heavy_optional_modules(tmp_path):
    """A whole `mehs fuse` run loads none of scipy.stats, colour, matplotlib or torch."""
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    sim = simulate_bracket(make_scene("window", 24, 24, seed=1), SensorModel(seed=3),
                           (0.05, 0.4, 3.2), seed=0)
    scene = write_simulated_scene(sim, tmp_path / "scene", scene_id="s")
    code = ("import sys\nfrom mehs.cli import main\n"
            f"rc = main(['fuse', {str(scene)!r}, '--out', {str(tmp_path / 'out')!r}])\n"
            "heavy = ('scipy.stats', 'colour', 'matplotlib', 'torch', 'dask', 'onnxruntime')\n"
            "print('LOADED', [m for m in heavy if m in sys.modules], rc)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "LOADED [] 0" in r.stdout, r.stdout + r.stderr[-2000:]


def test_uncached_kernel_notice(tmp_path, capsys, monkeypatch):
    from types import SimpleNamespace

    from mehs.synthesis import _numba_cache
    from mehs.synthesis._numba_cache import notice_if_uncached

    monkeypatch.setattr(_numba_cache, "_told", False)

    idx = tmp_path / "k.nbi"
    cache_file = SimpleNamespace(_index_path=str(idx))
    disp = SimpleNamespace(_cache=SimpleNamespace(_cache_file=cache_file))
    assert notice_if_uncached(disp) is True
    assert "compiling the merge kernels once" in capsys.readouterr().err
    assert notice_if_uncached(disp) is False       # once per process
    monkeypatch.setattr(_numba_cache, "_told", False)
    idx.write_bytes(b"")
    assert notice_if_uncached(disp) is False
    assert notice_if_uncached(object()) is False
