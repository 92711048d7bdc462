"""Start-up cost of the CLI paths (issue 16): light imports, same numbers."""

import numpy as np
import pytest
from _checks import MALLINFO2, has_mallinfo2


@pytest.mark.parametrize("n", [1, 9, 10, 11, 97, 4096, 10001])
@pytest.mark.parametrize("cut", [0.0, 0.1, 0.25])
def test_trim_mean_equals_scipy(n, cut):
    from scipy.stats import trim_mean

    from mehs.synthesis.noise import _trim_mean

    a = np.round(np.random.default_rng(n).normal(3, 5, n))   # many ties, like rounded darks
    assert _trim_mean(a, cut) == pytest.approx(trim_mean(a, cut), rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("p", [0.5, 1e-4, 1e-9, 0.95])
def test_chi2_quantiles_equal_scipy_stats(p):
    """mehs's χ² quantile (closed form at whole dof, scipy beyond) against scipy.stats."""
    from scipy import stats

    from mehs.synthesis.ghost import chdtri

    for dof in (np.arange(1, 1025), np.array([3, 1500, 4000]), np.array([0.5, 2.5, 7.0])):
        np.testing.assert_allclose(chdtri(dof, p), stats.chi2.isf(p, dof), rtol=1e-11)
    ints = np.array([[1, 2], [204, 407]], dtype=np.int32)
    assert chdtri(ints, p).shape == (2, 2)


def test_chi2_closed_form_refuses_what_it_cannot_do():
    from mehs.synthesis._chi2 import chi2_isf_integer

    with pytest.raises(ValueError, match="whole degrees of freedom"):
        chi2_isf_integer(np.array([0, 3]), 0.5)
    with pytest.raises(ValueError, match="whole degrees of freedom"):
        chi2_isf_integer(np.array([1.5]), 0.5)
    with pytest.raises(ValueError, match="p must be"):
        chi2_isf_integer(np.array([3]), 1.0)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("min_pixels,grow", [(3, 1), (1, 2), (5, 0), (2, 3)])
def test_ghost_mask_cleanup_equals_scipy_ndimage(seed, min_pixels, grow):
    """Dropping small 8-connected groups and growing the mask (OpenCV) as scipy.ndimage does."""
    from scipy import ndimage

    from mehs.synthesis.ghost import _finish

    rng = np.random.default_rng(seed)
    mask = rng.random((61, 47)) < 0.08
    mask[0, :5] = mask[-1, -4:] = mask[20:30, 0] = True       # groups touching the border
    want = mask.copy()
    if min_pixels > 1:
        lab, _ = ndimage.label(want, structure=np.ones((3, 3)))
        keep = np.bincount(lab.ravel()) >= min_pixels
        keep[0] = False
        want = keep[lab]
    if grow > 0:
        want = ndimage.binary_dilation(want, structure=np.ones((3, 3)), iterations=grow)
    got = _finish(mask, np.zeros(mask.shape, np.float32), 1.0, 1e-4, min_pixels, grow)
    np.testing.assert_array_equal(got.mask, want)
    assert got.fraction == pytest.approx(want.mean())


def _no_warm_up_running():
    """Wait for warm-up threads earlier tests left (a first-ever compile prints the notice)."""
    import threading

    for t in threading.enumerate():
        if t.name == "mehs-warm-merge":
            t.join(600)


def test_uncached_kernel_notice(tmp_path, capsys, monkeypatch):
    _no_warm_up_running()
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


def test_cli_small_pages_turns_numpy_huge_pages_off_unless_the_user_chose(monkeypatch):
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:
        from numpy.core.multiarray import _set_madvise_hugepage
    from mehs.cli import small_pages

    before = _set_madvise_hugepage(True)
    try:
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        assert small_pages() is False
        assert _set_madvise_hugepage(True) is True          # left as the user set it
        monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE")
        assert small_pages() is True
        assert _set_madvise_hugepage(True) is False         # small_pages turned it off
        # and in the processes it starts (build workers are spawned interpreters)
        import multiprocessing

        with multiprocessing.get_context("spawn").Pool(1) as pool:
            assert pool.apply(_hugepages_advised) is False
    finally:
        _set_madvise_hugepage(before)


def _hugepages_advised() -> bool:
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:
        from numpy.core.multiarray import _set_madvise_hugepage
    return bool(_set_madvise_hugepage(True))


def test_console_reuses_the_heap_for_fuse_only(monkeypatch):
    import sys

    import mehs.cli as cli

    calls = []
    monkeypatch.setattr(cli, "reuse_heap", lambda: calls.append(sys.argv[1]) or True)
    monkeypatch.setattr(cli, "small_pages", lambda: True)
    monkeypatch.setattr(cli, "main", lambda: 0)
    for argv in (["mehs", "fuse", "x"], ["mehs", "evaluate", "x"], ["mehs"]):
        monkeypatch.setattr(sys, "argv", argv)
        with pytest.raises(SystemExit):
            cli.console()
    assert calls == ["fuse"]


def test_reuse_heap_serves_mid_sized_arrays_from_the_glibc_heap():
    """After :func:`mehs.cli.reuse_heap` a 20 MB array comes from the heap (``arena``),
    not from its own mapping (``hblkhd``), so freed pages are used again."""
    import subprocess
    import sys

    code = MALLINFO2 + (
        "import numpy as np\n"
        "import sys\n"
        "if sys.argv[1] == 'on':\n"
        "    from mehs.cli import reuse_heap\n"
        "    assert reuse_heap()\n"
        "a = np.ones(5_000_000, np.float32)\n"
        "m = libc.mallinfo2()\n"
        "print('MMAPPED', m.hblkhd >= 20_000_000, 'HEAP', m.arena >= 20_000_000)\n")
    if not has_mallinfo2():
        pytest.skip("not glibc ≥ 2.33")
    off = subprocess.run([sys.executable, "-c", code, "off"], capture_output=True, text=True)
    on = subprocess.run([sys.executable, "-c", code, "on"], capture_output=True, text=True)
    assert off.returncode == 0 and on.returncode == 0, off.stderr + on.stderr
    assert "MMAPPED True HEAP False" in off.stdout
    assert "MMAPPED False HEAP True" in on.stdout


def test_console_runs_the_command_and_exits_with_its_code(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "mehs", "fuse", str(tmp_path / "missing"),
                        "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "mehs: error:" in r.stderr
    r = subprocess.run([sys.executable, "-m", "mehs", "--version"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and r.stdout.startswith("mehs ")


def test_the_compile_notice_names_the_kernel_the_merge_runs(monkeypatch):
    """The notice is about the kernel a merge is about to use (a linear sensor's Poisson
    merge compiles the one-pass kernel only: no notice about the stage kernel)."""
    from mehs.synthesis import merge as merge_mod
    from mehs.synthesis import _numba_cache
    from mehs.synthesis._merge_fused import merge_chunk_poisson_linear
    from mehs.synthesis._merge_fused_weighted import merge_chunk_debevec_linear
    from mehs.synthesis._merge_kernels import merge_chunk, merge_chunk_poisson
    from mehs.synthesis.response import ResponseCurve

    import threading

    _no_warm_up_running()
    seen = []
    me = threading.current_thread()
    # (a warm-up thread an earlier test started may still be merging: not counted)
    monkeypatch.setattr(_numba_cache, "notice_if_uncached",
                        lambda d, what="": (threading.current_thread() is me
                                            and seen.append(d)) or False)
    rng = np.random.default_rng(0)
    stack = [rng.integers(100, 3000, (3, 4, 5)).astype(np.uint16) for _ in range(3)]
    t = [1.0, 4.0, 16.0]
    merge_mod.merge_bracket(stack, t)
    merge_mod.merge_bracket(stack, t, method="debevec")
    curve = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5)) * 1.01, 12, "test")
    merge_mod.merge_bracket(stack, t, response=curve)
    merge_mod.merge_bracket(stack, t, method="robertson", response=curve)
    assert seen == [merge_chunk_poisson_linear, merge_chunk_debevec_linear, merge_chunk_poisson,
                    merge_chunk]


def test_the_stored_kernels_key_reads_numbas_version_without_scanning_distributions(
        monkeypatch, tmp_path):
    """The key of every stored kernel names numba's version; importlib.metadata found it by
    scanning every installed distribution (20–25 ms of each warm `mehs fuse`)."""
    import importlib.util
    from importlib import metadata
    from types import SimpleNamespace

    from mehs.synthesis import _native

    expected = metadata.version("numba")
    real = metadata.version

    def scanned(dist):
        raise AssertionError(f"scanned the installed distributions for {dist}")

    monkeypatch.setattr(metadata, "version", scanned)
    assert _native._numba_version() == expected
    # a numba without versioneer's file, or a source checkout's (whose version comes from
    # git; its literals say "0+unknown"), or a file recording an error: the metadata
    monkeypatch.setattr(metadata, "version", real)
    (tmp_path / "numba").mkdir()
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: SimpleNamespace(
        origin=str(tmp_path / "numba" / "__init__.py")))
    assert _native._numba_version() == expected
    q = "'" * 3
    for text in ('def get_versions():\n    return {"version": "0+unknown", "error": None}\n',
                 f'version_json = {q}\n{{"error": "no git", "version": "9.9"}}\n{q}\n',
                 f'version_json = {q}\n{{"error": null, "version": "0+untagged.1"}}\n{q}\n'):
        (tmp_path / "numba" / "_version.py").write_text(text)
        assert _native._numba_version() == expected, text
    (tmp_path / "numba" / "_version.py").write_text(
        f'version_json = {q}\n{{"error": null, "version": "9.9.9"}}\n{q}  # END\n')
    assert _native._numba_version() == "9.9.9"
