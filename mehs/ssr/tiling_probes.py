"""Probes of a torch network for tiled inference: memory per pixel, receptive field, grid.

Used by :mod:`mehs.ssr.tiling` (which re-exports the public names) to plan tiles:

- :func:`torch_memory_probe` — ``fixed + bytes_per_pixel × pixels`` of an inference,
  from the live tensors of two small runs (a dispatch mode counts them);
- :func:`torch_receptive_radius` — the margin that makes tiles exact, by autograd;
- :func:`torch_align` — the pooling grid tiles must sit on.

They depend on the architecture only; :mod:`mehs.ssr.probe_cache` keeps them on disk
for mehs's own networks.
"""

from __future__ import annotations

import contextlib
import math
import threading
import warnings

from typing import Callable

import numpy as np


def _round_up(n: int, a: int) -> int:
    return -(-n // a) * a


#: Sides of the two square probes of :func:`torch_memory_probe`. The slope
#: between them drops fixed costs (small hdrssr: 904 B/px from (96, 128), (128,
#: 192) and (192, 256) alike; the smallest pair costs 0.2 s).
MEMORY_PROBES = (96, 128)
#: Modules that evaluate large inputs in chunks (a ``chunk_pixels`` attribute, as
#: the mehs basis branches) get chunks of this share of the smaller probe's pixels
#: during the probes: both probes are then several chunks long, as a large image
#: is (see :func:`torch_memory_probe`; a quarter put both small-hdrssr probes and
#: both tiny-hdrssr test probes on the large-image line, half did not).
PROBE_CHUNK_SHARE = 0.25


def _generator(device):
    """A seeded generator for a probe's random input: the probes answer the same on
    every call, and leave the caller's torch random state as it was (a tiled call drew
    from it, so a user's seeded run went otherwise once tiles were probed)."""
    import torch

    g = torch.Generator(device=device)
    g.manual_seed(0x6D656873)
    return g


def probe_input(g, side: int, device, hdr: bool):
    """A probe's ``(1, 3, side, side)`` input from generator ``g``: uniform in [0, 1), or
    (``hdr``) that times a log-uniform brightness from 0.1 to 100 per pixel. The field
    probes run on both and take the union: a path open only on bright pixels (a gate
    past 1) is dead on the first, a path that saturates on bright ones on the second."""
    import torch

    x = torch.rand(1, 3, side, side, device=device, generator=g)
    if hdr:
        x *= 10.0 ** (torch.rand(1, 1, side, side, device=device, generator=g) * 3.0 - 1.0)
    return x


def _peak_mode(reorders: bool = True):
    """A torch dispatch mode whose ``peak`` is the most bytes of live tensors it saw.

    It sees every operator's outputs and counts each storage from its creation to
    its release (inputs made outside it and parameters not). With ``reorders``, at
    each convolution a copy of its input and output is added: oneDNN reorders both
    into its blocked layout, outside torch's tensors.
    """
    import weakref

    import torch
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_leaves

    conv = torch.ops.aten.convolution.default

    class Peak(TorchDispatchMode):
        @classmethod
        def _should_skip_dynamo(cls):
            # else torch wraps __torch_dispatch__ in torch._dynamo.disable, whose first
            # call imports torch._dynamo (1.4 s of CPU); nothing is compiled here
            return False

        def __init__(self):
            super().__init__()
            self.live = self.peak = 0
            self.held = set()

        def _release(self, key, n):
            self.live -= n
            self.held.discard(key)

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in tree_leaves(out):
                if isinstance(t, torch.Tensor):
                    s = t.untyped_storage()
                    if id(s) not in self.held:
                        self.held.add(id(s))
                        self.live += s.nbytes()
                        weakref.finalize(s, self._release, id(s), s.nbytes())
            now = self.live
            if reorders and func is conv:
                # the reorders copy the elements a call sees: a strip of a larger map
                # (a view) costs its own size, not its storage's
                now += args[0].numel() * args[0].element_size() + out.numel() * out.element_size()
            self.peak = max(self.peak, now)
            return out

    return Peak()


def _peak_tensor_bytes(network, side: int, width: int | None = None) -> tuple[int, int]:
    """Peak bytes of live tensors (plus convolution reorders, :func:`_peak_mode`) of one
    ``side × width`` call (``width``: ``side``), the input included; bytes per pixel of
    its output."""
    import torch

    param = next(network.parameters(), None)
    device = param.device if param is not None else "cpu"
    width = side if width is None else int(width)
    with torch.no_grad(), _peak_mode() as mode:
        y = network(torch.rand(1, 3, side, width, device=device, generator=_generator(device)))
        bands = int(y.shape[1]) * y.element_size()
        del y
    return mode.peak, bands


def _chunked_modules(network) -> list:
    """Modules of ``network`` that evaluate large inputs in chunks of ``chunk_pixels`` pixels."""
    return [m for m in network.modules()
            if isinstance(getattr(m, "chunk_pixels", None), int) and m.chunk_pixels > 0]


@contextlib.contextmanager
def _probe_chunks(modules, pixels: int):
    """Context: ``modules`` evaluate in chunks of ``pixels`` (their own setting restored after)."""
    own = [(m, m.__dict__.get("chunk_pixels")) for m in modules]
    try:
        for m in modules:
            m.chunk_pixels = int(pixels)
        yield
    finally:
        for m, v in own:
            if v is None:
                del m.__dict__["chunk_pixels"]
            else:
                m.chunk_pixels = v


def torch_memory_probe(network, *, sizes: tuple[int, int] = MEMORY_PROBES) -> dict:
    """Memory of a torch network's inference, ``fixed + per pixel × pixels``, from two probes.

    Each probe runs the network (no autograd) on a random square input while
    counting the bytes of live tensors (:func:`_peak_tensor_bytes`); the slope
    between the two peaks is the memory per pixel, its intercept the fixed part
    (such as a buffer of fixed size). The allocator's share comes on top
    (:func:`allocator_overhead`).

    Modules that evaluate in chunks (``chunk_pixels``) make the peak a maximum
    of two lines: below the chunk size their temporaries grow with the image,
    above it they are fixed and the rest of the network sets the slope. Probes
    smaller than a real chunk measured the first line (1.37 kB/px for the small
    hdrssr net, against 0.90 kB/px for any large image). So the slope is measured
    with chunks of :data:`PROBE_CHUNK_SHARE` of the smaller probe, and the fixed part is raised so
    that the line also covers the larger probe run with the modules' own chunks:
    a line with the large-image slope through that point lies above both.

    Returns
    -------
    ``{"bytes_per_pixel", "fixed_bytes", "out_bytes_per_pixel", "allocator"}``:
    the counted model, the bytes per image pixel of the stitched output
    (bands × 4) and ``"heap"`` (apply :func:`allocator_overhead`); with
    ``"bytes_per_column"`` (per pixel of the image's width) for a network that
    streams its rows (:func:`_streamed_memory_probe`).
    """
    s1, s2 = sorted(int(s) for s in sizes)
    n1, n2 = s1 * s1, s2 * s2
    chunked = _chunked_modules(network)
    streamed = _streamed_modules(network)
    if streamed:
        return _streamed_memory_probe(network, chunked, streamed, s1, s2)
    with _probe_chunks(chunked, max(256, int(PROBE_CHUNK_SHARE * n1))):
        (p1, bands), (p2, _) = _peak_tensor_bytes(network, s1), _peak_tensor_bytes(network, s2)
    slope = (p2 - p1) / (n2 - n1) if n2 > n1 else 0.0
    if slope <= 0:                    # no growth seen: the larger probe's mean, no fixed part
        slope, fixed = p2 / n2, 0.0
    else:
        fixed = max(0.0, p2 - slope * n2)
    if chunked:
        # a run more than two of the modules' own chunks large: their full temporaries,
        # and the buffers a call of several strips has (at exactly one chunk the strip
        # convolutions ran as one whole call, 8 MiB less than any larger image; in-place
        # strips keep two finished strips until no later strip reads their rows)
        side = max(s2, math.isqrt(2 * max(int(m.chunk_pixels) for m in chunked)) + 1)
        own, _ = _peak_tensor_bytes(network, side)
        fixed = max(fixed, own - slope * side * side)
    return {"bytes_per_pixel": slope, "fixed_bytes": fixed,
            "out_bytes_per_pixel": float(bands), "allocator": "heap"}


def _streamed_modules(network) -> list:
    """Modules that sweep an image down its rows keeping a window of rows alive
    (``stream_window_rows(width) -> rows``, 0 where they do not): their memory grows
    with the image's width, not its pixels (HSCNN-D, :mod:`mehs.ssr.net.hscnnd_stream`)."""
    return [m for m in network.modules()
            if callable(getattr(m, "stream_window_rows", None)) and m.stream_window_rows(64)]


def _streamed_memory_probe(network, chunked, streamed, s1: int, s2: int) -> dict:
    """:func:`torch_memory_probe` of a network with streamed modules:
    ``fixed + per pixel × pixels + per column × width``.

    A window of rows as wide as the image is ``per column``: square probes cannot tell
    it from ``per pixel`` (a line through 96² and 128² put the full HSCNN-D at 2.6 GB
    for 2048×1024, which holds 0.6 GB of window). Three probes taller than the window
    part the terms: two heights at one width (per pixel), two widths at one height
    (per column). The line is then raised to cover a square run with the modules' own
    chunks, as for any chunked network.
    """
    w1, w2 = max(8, s1 // 3), 2 * max(8, s1 // 3)
    chunk = max(256, int(PROBE_CHUNK_SHARE * s1 * s1))
    with _probe_chunks(chunked, chunk):
        win = max(int(m.stream_window_rows(w)) for m in streamed for w in (w1, w2))
        h1 = max(s1, 2 * win + 2)
        h2 = 2 * h1
        (p1, bands) = _peak_tensor_bytes(network, h1, w1)
        p2, _ = _peak_tensor_bytes(network, h2, w1)
        p3, _ = _peak_tensor_bytes(network, h1, w2)
    slope = (p2 - p1) / ((h2 - h1) * w1)
    if slope <= 0:                    # no growth seen: the taller probe's mean
        slope, column, fixed = p2 / (h2 * w1), 0.0, 0.0
    else:
        column = max(0.0, (p3 - p1) / (w2 - w1) - slope * h1)
        fixed = max(0.0, p1 - slope * h1 * w1 - column * w1)
    others = [m for m in chunked if not any(m is s for s in streamed)]
    if others:
        # (a streamed module's steps are rows, not chunks: the square run of the others'
        # own chunks costs 5 s for HSCNN-D full, and only for them)
        side = max(s2, h1, math.isqrt(2 * max(int(m.chunk_pixels) for m in others)) + 1)
        own, _ = _peak_tensor_bytes(network, side)
        fixed = max(fixed, own - slope * side * side - column * side)
    return {"bytes_per_pixel": slope, "fixed_bytes": fixed, "bytes_per_column": column,
            "out_bytes_per_pixel": float(bands), "allocator": "heap"}


def torch_bytes_per_pixel(network, *, probe: int = MEMORY_PROBES[0]) -> float:
    """Memory per pixel of a torch network's inference (probes of ``probe`` and 1.5 × ``probe``).

    See :func:`torch_memory_probe` (this is its ``bytes_per_pixel``, as counted; for a
    network streaming its rows, with its memory per column spread over a ``probe``-pixel
    tall square's pixels, which is more than a taller image's per pixel).
    """
    m = torch_memory_probe(network, sizes=(probe, probe * 3 // 2))
    return m["bytes_per_pixel"] + m.get("bytes_per_column", 0.0) / probe


#: Margin used when a network's gradient reaches the whole probe (a global
#: operation such as non-local attention over all pixels, or a field wider
#: than the largest probe): tiles are then approximate whatever the margin. It also
#: marks that verdict, so it is one no tiling probe measures: probes run on the tile
#: grid (at least 8), whose margins are multiples of it (64 was: a real 64-pixel field,
#: MST++ with a 3-block bottleneck, was taken for a global operation).
GLOBAL_MARGIN = 65


#: Resident bytes per counted byte assumed for a receptive-field probe (autograd
#: keeps every layer's output; the C heap holds more than the tensors).
RADIUS_PROBE_OVERHEAD = 1.5


class FieldWiderThanBudget(Exception):
    """The receptive field filled the largest probe the memory budget allows.

    Not a global operation, and not a property of the architecture (a larger budget
    measures it): ``lower_bound`` is the least radius the field can have, on the grid.
    """

    def __init__(self, lower_bound: int, probe: int, needed: int | None = None):
        super().__init__(f"receptive field wider than a {probe}-pixel probe")
        self.lower_bound, self.probe = int(lower_bound), int(probe)
        #: bytes the next probe would have needed (None: unknown)
        self.needed = None if needed is None else int(needed)


def torch_receptive_radius(network, *, probe: int = 128, max_probe: int = 512,
                           align: int = 1, max_bytes: int | None = None) -> int:
    """Receptive-field radius (pixels) of a torch network's local part, measured by autograd.

    The gradient of an output pixel w.r.t. the input is non-zero exactly inside
    its receptive field, wherever its paths are open: the probes run on two inputs
    (:func:`probe_input`: [0, 1), and brightness spanning 0.1–100) and take the union. A global average (the channel attention of
    :mod:`mehs.ssr.net.layers`) or a channel similarity over all pixels (MST++'s
    spectral-wise attention) would spread it over the whole probe, so these
    statistics are detached during the probe: the radius is that of the
    convolutions, poolings and up-samplings. The probe doubles until the field fits inside it;
    a field still filling a ``max_probe`` probe (another global operation)
    gives :data:`GLOBAL_MARGIN`.

    With ``align > 1`` the result is the tile margin that makes tiles whose
    edges lie on that grid exact: behind a pooling the field depends on the
    pixel's phase on the grid (small hdrssr: 54 px right of a pixel at phase 0,
    59 px at phase 3). The gradient of the ``align × align`` block of outputs
    at an aligned centre bounds every phase at once: with ``L`` and ``R`` its
    field's reach left of and right of the block's first pixel, a pixel at
    phase ``p`` reaches at most ``L − p`` left and ``R − p`` right, so a margin
    of ``round_up(L, align)`` covers a tile's leading edge and
    ``round_up(R − align + 1, align)`` its trailing edge (both on the grid).

    ``max_bytes``: a larger probe runs only if the memory the last one held, scaled to
    its size (× :data:`RADIUS_PROBE_OVERHEAD`), fits. Autograd keeps every layer's
    output, ~24× what the inference holds: the full-size paper network's 512² probe
    held 9 GB and took 23 s to find its field (~400 px) wider than the probe anyway;
    MST++'s 256² probe, the one its 112-px field needs, held 2.6 GB. Where the next
    gradient probe does not fit, the field is measured in forward mode
    (:func:`_forward_mode_margin`: a Jacobian-vector product keeps the layers' outputs
    an inference keeps, with their tangents — MST++ full at 256²: 1.0 GB resident
    against the gradient's 2.6 GB) — the same margin; where that does not fit either,
    or the network has an operator without a forward-mode derivative,
    :class:`FieldWiderThanBudget` is raised with the half-width of the largest probe the
    field filled: a lower bound. (A margin read off how fast the field's influence
    decays was tried and dropped: measured on the probe's random input it missed a
    gate that opens on brighter pixels, and tiles were 4e-2 of the range off, silently.)
    """
    import torch

    # global statistics (channel attention's means, spectral-wise attention's channel
    # similarity) leave autograd: the probes measure the network's local field only
    from mehs.ssr.net.pooling import detached_statistics

    param = next(network.parameters(), None)
    device = param.device if param is not None else "cpu"
    a = max(1, int(align))
    forward_mode = False
    need = None          # bytes the next (gradient, then forward-mode) probe needs
    filled = probe       # the largest probe the field has filled
    while True:
        c = probe // 2 // a * a
        if forward_mode:
            try:
                margin, held = _forward_mode_margin(network, probe, a, device)
            except (NotImplementedError, RuntimeError) as e:
                if not _no_forward_derivative(e):
                    raise
                # an operator without a forward-mode derivative: the gradient's bound
                raise FieldWiderThanBudget(_round_up(filled // 2, a), filled, need) from None
            if margin is not None:
                return margin
        else:
            held, grad = 0, None
            for hdr in (False, True):
                g = _generator(device)
                x = probe_input(g, probe, device, hdr).requires_grad_()
                with detached_statistics(), _peak_mode(reorders=False) as mode:
                    block = network(x)[0, :, c:c + a, c:c + a]
                    # a random cotangent: the bands' plain sum is constant for a network
                    # whose bands are centred on their mean, and its gradient, zero, read
                    # as no field at all
                    block.backward(torch.randn(block.shape, device=block.device,
                                               dtype=block.dtype, generator=g))
                    del block
                held = max(held, mode.peak)
                here = x.grad[0].abs().sum(0).cpu().numpy() > 0
                grad = here if grad is None else grad | here
                del x
                network.zero_grad(set_to_none=True)
            ys, xs = np.nonzero(grad)
            if ys.size == 0:
                return 0
            lo, hi = min(ys.min(), xs.min()), max(ys.max(), xs.max())
            if lo > 0 and hi < probe - 1:
                reach_lo, reach_hi = int(c - lo), int(hi - c)
                if a == 1:
                    return max(reach_lo, reach_hi)
                return max(_round_up(reach_lo, a), _round_up(max(0, reach_hi - a + 1), a))
        filled = probe
        if probe >= max_probe:
            return GLOBAL_MARGIN
        need = held * 4 * RADIUS_PROBE_OVERHEAD
        if max_bytes is not None and need > max_bytes:
            if forward_mode:
                # the field reaches past the probe's edge from a centre probe // 2 away
                raise FieldWiderThanBudget(_round_up(probe // 2, a), probe, need)
            # measure what forward mode holds on this size before it grows
            forward_mode = True
            continue
        probe *= 2


#: One forward-mode probe at a time: torch has one dual level per process, and a second
#: thread's ``dual_level()`` fails ("Nested forward mode AD is not supported"), which
#: read as a network without forward-mode derivatives (a lower bound, cached).
_FORWARD_MODE = threading.Lock()


def _no_forward_derivative(e: BaseException) -> bool:
    """Whether ``e`` says an operator has no forward-mode derivative (not, say, that
    memory ran out, which is no property of the network to keep in the probe cache)."""
    if isinstance(e, NotImplementedError):
        return True
    text = str(e).lower()
    if "nested" in text:           # another forward-mode level open (user code elsewhere)
        return False
    return "forward" in text and ("not implemented" in text or "not supported" in text
                                  or "does not support" in text or "jvp" in text)


def _forward_mode_margin(network, probe: int, a: int, device) -> tuple[int | None, int]:
    """The margin :func:`torch_receptive_radius` measures, from one Jacobian-vector
    product; None where the field fills the ``probe²`` probe. Also the bytes it held.

    The tangent of a random perturbation of the ``a × a`` input block at an aligned
    centre ``c`` is non-zero at the outputs whose field holds that block. An output
    ``o = c + k·a + q`` at grid phase ``q`` reaching ``L_q`` left and ``R_q`` right is
    reached iff ``o − L_q ≤ c + a − 1`` and ``o + R_q ≥ c``, so per phase the last
    output reached gives ``round_up(L_q − q, a) = o_last − c − q`` (the gradient's
    leading margin is the largest over the phases) and the first one
    ``round_up(R_q + q − a + 1, a) = c + q − o_first`` (its trailing margin): the
    gradient probe's margin, exactly.
    """
    import torch
    from torch.autograd import forward_ad

    from mehs.ssr.net.pooling import detached_statistics, plain_graph

    c = probe // 2 // a * a
    reached, held = None, 0
    for hdr in (False, True):
        g = _generator(device)
        x = probe_input(g, probe, device, hdr)
        v = torch.zeros_like(x)
        v[..., c:c + a, c:c + a] = torch.randn(1, 3, a, a, device=device, generator=g)
        with _FORWARD_MODE, torch.no_grad(), plain_graph(), detached_statistics(), \
                _peak_mode(reorders=False) as mode, forward_ad.dual_level():
            tangent = forward_ad.unpack_dual(network(forward_ad.make_dual(x, v))).tangent
            # None: nothing depends on the input
            here = (np.zeros((probe, probe), bool) if tangent is None
                    else (tangent[0] != 0).any(0).cpu().numpy())
            del tangent
        held = max(held, mode.peak)
        reached = here if reached is None else reached | here
        del x, v
    return margin_from_reached(reached, c, a), held


def margin_from_reached(reached: np.ndarray, c: int, a: int) -> int | None:
    """The margin of a field, from the outputs ``reached (P, P)`` bool that a change of the
    ``a × a`` input block at ``(c, c)`` moves (see :func:`_forward_mode_margin`); None where
    they touch the probe's edge (the field may reach past it), 0 where there are none."""
    rows, cols = np.nonzero(reached.any(1))[0], np.nonzero(reached.any(0))[0]
    if rows.size == 0:
        return 0
    if (min(rows.min(), cols.min()) == 0
            or rows.max() == reached.shape[0] - 1 or cols.max() == reached.shape[1] - 1):
        return None
    lead = trail = 0
    for idx in (rows, cols):
        phase = (idx - c) % a
        for q in np.unique(phase):
            at = idx[phase == q]
            lead = max(lead, int(at.max()) - c - int(q))
            trail = max(trail, c + int(q) - int(at.min()))
    return max(lead, trail)


def torch_align(network, *, max_pixels: int | None = None, multiple: int = 1) -> int:
    """Tile grid of a torch network: at least 8, a multiple of ``2**depth`` of its deepest
    declared pooling stack, and of every down-sampling its operators perform
    (:func:`mehs.ssr.tiling_grid.torch_grid`, which ``max_pixels`` and ``multiple``
    are handed to: a network that declares nothing, a user's U-Net, is measured)."""
    from mehs.ssr.tiling_grid import torch_grid

    depths = [int(getattr(m, "depth")) for m in network.modules()
              if isinstance(getattr(m, "depth", None), int)]
    declared = max([8] + [2 ** d for d in depths])
    return math.lcm(declared, torch_grid(network, max_pixels=max_pixels, multiple=multiple))


def once(fn: Callable[[], int]) -> Callable[[], int]:
    """``fn``, called at most once."""
    done: list[int] = []

    def call() -> int:
        if not done:
            done.append(fn())
        return done[0]
    return call


def within_known_bound(store, budget: int, measure: Callable[[], int]) -> int:
    """``measure()``, unless ``store`` (a :class:`~mehs.ssr.probe_cache.ProbeStore`, or
    None) keeps a field bound that ``budget`` cannot measure past (raised again at once:
    the full paper network's probes cost ~6 s a process); a
    :class:`FieldWiderThanBudget` from ``measure`` is kept there with the bytes the next
    probe needs, which a larger budget measures."""
    bound = store.get("margin_bound") if store is not None else None
    if bound is not None and budget < bound.get("needed", 0):
        raise FieldWiderThanBudget(bound["lower_bound"], bound["probe"], bound["needed"])
    try:
        return measure()
    except FieldWiderThanBudget as e:
        if store is not None and e.needed is not None:
            store.put("margin_bound", {"needed": e.needed, "lower_bound": e.lower_bound,
                                       "probe": e.probe})
        raise


def margin_or_bound(model, measure: Callable[[], int]) -> Callable[[], int]:
    """``measure``, or the least radius the field can have where it is wider than any
    probe the budget allows (:class:`FieldWiderThanBudget`): with a warning, and marked in
    ``model._tiling_probe["margin_bound"]``, so that it is not taken for a global
    operation's :data:`GLOBAL_MARGIN`. The bound holds for one call (the probe cache keeps
    it for the budgets that cannot measure the field; a larger one measures it).
    (A field that fills even the largest probe, 512 px, still counts as global.)"""
    def call() -> int:
        try:
            return measure()
        except FieldWiderThanBudget as e:
            model.__dict__.setdefault("_tiling_probe", {})["margin_bound"] = True
            warnings.warn(f"{getattr(model, 'name', 'model')}: its receptive field is wider "
                          f"than a {e.probe}-pixel probe, the largest the memory budget allows "
                          f"to measure; tiles use a {e.lower_bound}-pixel margin and may differ "
                          "from whole-image inference near their seams (with more memory, "
                          "MEHS_TILE_MEMORY, a larger probe measures it)",
                          RuntimeWarning, stacklevel=2)
            return e.lower_bound
    return call
