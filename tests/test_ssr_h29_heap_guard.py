"""Tiles on the reused C heap return its free memory before a tile that would pass the
budget (issue 16: the paper network's full preset, tiled under a 1.5 GB cap, held 1.81 GB
as the heap's holes grew over the tiles)."""

import itertools

import numpy as np
import pytest

from mehs.ssr import tiling


def test_the_heap_is_returned_only_where_the_budget_is_short(monkeypatch):
    rss, trims = [0], []

    def trim():
        trims.append(rss[0])
        rss[0] = 10

    monkeypatch.setattr(tiling, "_rss", lambda: rss[0])
    monkeypatch.setattr(tiling, "_trim_heap", trim)
    record = {}
    guarded = tiling._heap_guard(lambda x: x + 1, 100, 30, record)
    rss[0] = 70                                        # 70 + 30 fits 100
    assert guarded(1) == 2 and trims == [] and record["heap_trims"] == 0
    rss[0] = 71
    assert guarded(2) == 3 and trims == [71] and record["heap_trims"] == 1


def test_tiles_under_a_short_budget_run_guarded(monkeypatch):
    # a tile budget far under what the process holds: every tile is preceded by a trim,
    # and the output is the unguarded tiles' own
    from types import SimpleNamespace

    calls = []

    def fn(x):
        calls.append(x.shape)
        return np.repeat(x[..., :1], 4, axis=2) * 2.0

    rgb = np.random.default_rng(0).random((64, 96, 3), dtype=np.float32)
    trims = []
    monkeypatch.setattr(tiling, "_trim_heap", lambda: trims.append(1))
    # (the process grows by 1 MiB at each look: far past a 0.2 MB tile budget)
    grown = itertools.count()
    monkeypatch.setattr(tiling, "_rss", lambda: next(grown) * 2**20)
    model = SimpleNamespace(tiling={"max_bytes": 200 * 48 * 48, "statistics": "tile"}, name="m")
    # (memory on the C heap: the tiles run on the heap kept for reuse, where trims act)
    probes = {"bytes_per_pixel": lambda: {"bytes_per_pixel": 100.0, "allocator": "heap"},
              "margin": lambda: 4, "align": lambda: 8}
    out = tiling.tiled_network_call(model, fn, rgb, probes)
    np.testing.assert_allclose(out, np.repeat(rgb[..., :1], 4, axis=2) * 2.0, rtol=1e-6)
    if not model._tiling_last["heap_reuse"]:
        pytest.skip("no glibc heap to keep for reuse here")
    assert len(calls) > 1 and model._tiling_last["heap_trims"] == len(trims) == len(calls)


def test_without_a_way_to_read_the_resident_memory_tiles_run_unguarded(monkeypatch):
    from types import SimpleNamespace

    def no_proc():
        raise FileNotFoundError("/proc/self/statm")

    monkeypatch.setattr(tiling, "_rss", no_proc)
    rgb = np.random.default_rng(0).random((64, 96, 3), dtype=np.float32)
    model = SimpleNamespace(tiling={"max_bytes": 200 * 48 * 48, "statistics": "tile"}, name="m")
    probes = {"bytes_per_pixel": lambda: {"bytes_per_pixel": 100.0, "allocator": "heap"},
              "margin": lambda: 4, "align": lambda: 8}
    out = tiling.tiled_network_call(model, lambda x: x * 2.0, rgb, probes)
    np.testing.assert_allclose(out, rgb * 2.0, rtol=1e-6)
