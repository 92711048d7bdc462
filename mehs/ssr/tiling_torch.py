"""Tiled inference of torch SSR networks: their probes, and image-wide statistics.

:func:`tiled_torch_call` is the tiling hook of the torch models
(:class:`mehs.ssr.net.export.TorchSSRModel` and user TorchScript / module models):
it measures the network (memory, receptive field, grid: :mod:`mehs.ssr.tiling_probes`,
kept on disk by :mod:`mehs.ssr.probe_cache` for mehs's own networks) and hands the
plan to :func:`mehs.ssr.tiling.tiled_network_call`. Where a network's global
operations are statistics that tiles can assemble (channel attention's means,
MST++'s channel similarity: :func:`mehs.ssr.net.pooling.image_statistic`), the tiles
run with the whole image's (:mod:`mehs.ssr.tiling_global`); the output then equals
whole-image inference to float rounding.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mehs.errors import InputError
from mehs.ssr.tiling import default_budget, env_max_bytes, probe_budget, tiled_network_call
from mehs.ssr.tiling_blend import predict_tiled
from mehs.ssr.tiling_pad import grid, padded, padded_torch_module, size_multiple
from mehs.ssr.tiling_probes import (GLOBAL_MARGIN, margin_or_bound, once, torch_align,
                                    torch_memory_probe, torch_receptive_radius,
                                    within_known_bound)


def tiled_torch_call(model, rgb: np.ndarray,
                     whole: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """``model.network`` (torch, eval mode) on ``rgb (H, W, 3)`` → ``(H, W, B)``, tiled when large.

    The probes measure the network's memory (:func:`torch_memory_probe`), its
    margin (:func:`torch_receptive_radius` on its pooling grid: tiles then agree
    with whole-image inference wherever the network is local) and its grid.
    ``whole``: how the model runs one image or tile ``(h, w, 3)`` → ``(h, w, B)`` (its
    own checks and conversions), else ``model.network`` on it; the probes run
    ``model.network``.
    """
    import torch

    k = size_multiple(model)

    if whole is None:
        def whole(x: np.ndarray) -> np.ndarray:
            t = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))[None]).to(model.device)
            with torch.no_grad():
                y = model.network(t)[0].permute(1, 2, 0)
            # (under autocast a network returns half floats, which numpy has no bfloat16 for)
            return y.to(device="cpu", dtype=torch.float32).numpy()

    run = padded(whole, k, getattr(model, "name", "model"))
    net = model.network
    # the probes run the network on sizes of their own: padded to the multiple too
    probed = padded_torch_module(net, k)

    given = getattr(model, "tiling", None)
    opts = given if isinstance(given, dict) else {}
    cached = model.__dict__.get("_tiling_probe", {})
    from mehs.ssr.probe_cache import graph_signature

    signature = graph_signature(net)
    if cached.get("graph", signature) != signature:
        # a hook set, autocast entered, strips resized since the probes ran: another
        # inference path (a hooked HSCNN-D holds its dense features, not a window of
        # rows) and, for a hook, maybe another field: every probe is stale
        cached.clear()
    model.__dict__.setdefault("_tiling_probe", cached)["graph"] = signature
    if cached.pop("margin_bound", False):
        # a lower bound is this call's answer only: a later budget may measure the field
        cached.pop("margin", None)

    cap = getattr(net, "max_tile_pixels", None)
    # measured once per architecture, not once per process (mehs's own networks;
    # one padded to a multiple measures its padded calls: not cached)
    store = None
    if cap is None and k == 1:
        from mehs.ssr.probe_cache import ProbeStore

        store = ProbeStore.for_network(net)

    def margin() -> int:
        from mehs.ssr.allocator import trim_heap

        # the probes keep within the memory a tile may have
        budget = probe_budget(opts)

        def measure() -> int:
            with torch.enable_grad():
                return torch_receptive_radius(probed, align=grid(align(), k),
                                              max_bytes=budget)
        try:
            return within_known_bound(store, budget, measure)
        finally:
            net.zero_grad(set_to_none=True)
            # the probes' layer outputs are freed to the C heap, which keeps them
            # resident: the tiles' budget was measured before (the full paper network's
            # forward-mode probe left 0.4 GB, and the tiled call peaked at 3.1 GB)
            trim_heap()

    def memory() -> dict:
        if cap is None:
            return torch_memory_probe(probed)
        # memory super-linear in the tile (global attention): small probes, and the
        # network says how large a tile fits the budget; the per-pixel figure is raised
        mem = torch_memory_probe(probed, sizes=(32, 48))
        budget = env_max_bytes() or default_budget()
        mem["bytes_per_pixel"] = max(mem["bytes_per_pixel"], budget / cap(budget))
        mem["allocator"] = None          # the cap already is a resident-memory figure
        return mem

    def measure_align() -> int:
        # the grid probe runs the network whole on 384×256 (and its transpose and half):
        # a smaller probe blurs the sizes of a network that pads to its grid, and the grid
        # read off them was wrong; only a network whose memory grows faster than its
        # input (a max_tile_pixels cap) gets one that fits
        limit = None if cap is None else cap(probe_budget(opts))
        return torch_align(probed, max_pixels=limit, multiple=k)

    # the margin probe needs the grid first: one measurement for both
    align = once(measure_align)
    # (a declared receptive_radius only raises the measured margin, _with_declared_radius:
    # it is not in the probe cache's key and goes stale when a part is replaced)
    fixed_margin = getattr(net, "TILING_MARGIN", None)
    probes = {"bytes_per_pixel": memory,
              "margin": (lambda: int(fixed_margin)) if fixed_margin is not None else margin,
              "align": align}
    if store is not None:
        probes = {name: store.measured(kind, probes[name])
                  for name, kind in (("bytes_per_pixel", "memory"), ("margin", "margin"),
                                     ("align", "align"))}
        # the margin probe reads the grid through the store too
        align = probes["align"] = once(probes["align"])
    probes["margin"] = _with_declared_radius(net, margin_or_bound(model, probes["margin"]),
                                             lambda: grid(align(), k))
    from mehs.ssr.probe_cache import cacheable

    # a user's network is checked on a probe image (mehs's own are, in the test suite);
    # (not its cache key, which hashes the network package's sources: 5 ms every call)
    user = not cacheable(net)
    probes["check_tiles"] = lambda record: user
    return tiled_network_call(model, run, rgb, probes, image_means=_image_means_stitcher(model))


def _with_declared_radius(net, margin: Callable[[], int], align: Callable[[], int]):
    """The margin probe, raised to a zoo network's declared ``receptive_radius`` (on the
    grid) where that is wider: a field probe sees only the paths its inputs open (HSCNN-D
    full: 24 px measured, 31 by construction). The declaration is read per call, never
    cached with the architecture's probes, and never lowers what was measured (a part
    replaced by a wider one leaves it stale); a global operation stays global."""
    from mehs.ssr.net.base import SSRNetwork

    def raised() -> int:
        m = margin()
        declared = getattr(net, "receptive_radius", None) if isinstance(net, SSRNetwork) else None
        if m == GLOBAL_MARGIN or not isinstance(declared, int) or declared <= 0:
            return m
        a = max(1, int(align()))
        return max(int(m), -(-declared // a) * a)

    return raised


def _image_means_stitcher(model) -> Callable[..., np.ndarray]:
    """The ``image_means`` of :func:`tiled_network_call` for ``model.network``.

    A network without layers whose global statistics tiles can assemble (modules that
    declare ``image_statistics = True``: channel attention, MST++'s spectral-wise
    attention; :func:`mehs.ssr.net.pooling.image_statistic`) is local: plain tiles
    already equal the whole image. One with other global operations (a measured margin
    of :data:`GLOBAL_MARGIN`, or a ``max_tile_pixels`` cap: AWAN's non-local attention)
    gets each tile's own statistics, or is refused when ``strict``.
    ``_tiling_last["statistics"]`` says which ran ("image" or "tile").
    """
    from mehs.ssr.tiling_global import predict_tiled_image_means, warn_tiles_differ

    net = model.network

    def stitch(fn, rgb, plan, strict):
        record = model.__dict__.setdefault("_tiling_last", {})
        probe = model.__dict__.get("_tiling_probe", {})
        is_global = probe.get("margin") == GLOBAL_MARGIN and not probe.get("margin_bound")
        if getattr(net, "max_tile_pixels", None) is not None or is_global:
            if strict:
                raise InputError(f"{getattr(model, 'name', type(net).__name__)}: its global "
                                 "operations are not statistics tiles can assemble (average "
                                 "poolings, spectral-wise attention), so tiles cannot equal "
                                 "the whole image; use tiling statistics 'tile' or 'off'")
            warn_tiles_differ(model, "its global operations are not statistics tiles can "
                                     "assemble")
            return predict_tiled(fn, rgb, plan)
        if not any(getattr(m, "image_statistics", False) is True for m in net.modules()):
            return predict_tiled(fn, rgb, plan)       # local: plain tiles are exact
        record["statistics"] = "image"
        return predict_tiled_image_means(fn, rgb, plan, record=record,
                                         multiple=size_multiple(model))
    return stitch
