"""numba's cache of the merge kernels follows every source they inline."""

from __future__ import annotations

from pathlib import Path


def test_an_edit_to_an_inlined_module_drops_the_cached_kernels(monkeypatch, tmp_path):
    """numba checks only the compiled function's own file: an edit to ``_merge_rows.py`` left
    ``_merge_kernels``' cached machine code (the old arithmetic) in use. The kernels' caches
    are keyed on all their sources: a changed digest removes them, an unchanged one keeps
    them, other modules' caches are left alone."""
    from mehs.synthesis import _numba_cache as nc

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    import numba.core.config as cfg

    monkeypatch.setattr(cfg, "CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(nc, "_checked", False)
    nc.drop_stale_kernel_caches()                      # records the digest
    stamps = list(tmp_path.rglob(nc._STAMP))
    assert stamps
    d = stamps[0].parent
    cached = d / "_merge_kernels.merge_chunk-83.py311.nbi"
    other = d / "somebody_else.f-1.py311.nbi"
    for f in (cached, other):
        f.write_bytes(b"x")
    monkeypatch.setattr(nc, "_checked", False)
    nc.drop_stale_kernel_caches()                      # sources unchanged: kept
    assert cached.exists()
    stamps[0].write_text("0" * 64 + "\n")              # as if _merge_rows.py had changed
    monkeypatch.setattr(nc, "_checked", False)
    nc.drop_stale_kernel_caches()
    assert not cached.exists() and other.exists()
    assert stamps[0].read_text().strip() != "0" * 64
    assert Path(nc.__file__).parent.joinpath("_merge_rows.py").is_file()


def test_every_source_of_a_stored_kernel_is_followed_by_numbas_cache_too():
    """The stored kernels' key lists their sources (``_native_specs``); numba's own cache of
    the same kernels must follow the same files (review, session 35: the binned weighted
    kernels' module was missing, and an edit to ``_bin_statistic`` left their cached
    machine code — the old statistic — in use)."""
    from mehs.synthesis import _native_specs
    from mehs.synthesis._numba_cache import KERNEL_MODULES

    for kind, spec in _native_specs.KERNELS.items():
        stems = {Path(f).stem for f in spec.sources} | {spec.module.rsplit(".", 1)[1]}
        assert stems <= set(KERNEL_MODULES), (kind, stems - set(KERNEL_MODULES))
