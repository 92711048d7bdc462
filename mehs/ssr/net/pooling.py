"""Global statistics that tiled inference can make image-wide (issue 16).

The channel attention of mehs's networks (squeeze-and-excitation,
:class:`mehs.ssr.net.layers.ChannelAttention`) scales each feature map by a function of
its mean over the *whole* input; MST++'s spectral-wise attention
(:class:`mehs.ssr.net.mstpp2022.SpectralMSA`) mixes channels by their cosine similarity
over all pixels. Run tile by tile, each tile sees its own statistics, so the output
differs from whole-image inference however wide the margin (up to ~1e-3 of the output's
range for a trained paper network, ~2e-3 for an MST++ with trained-like attention). A
mean, a Gram matrix and a squared norm are sums over pixels, though, and sums can be
assembled from tiles. Such layers call :func:`image_statistic` (:func:`pooled_mean` for
a mean) and declare ``image_statistics = True``; inside an :class:`ImageMeans` context it

- adds, for the tile about to run, each layer's sum over the part of the image that
  tile *owns* (the owned parts partition the padded image on the pooling grid, and
  lie where the tile's features equal the whole image's: at least a margin from a
  shared edge), and
- hands every layer the image-wide statistic of the previous run instead of the tile's.

:func:`mehs.ssr.tiling_global.predict_tiled_image_means` runs the tiles until the
statistics it hands out are those the run measures (a fixed point: whole-image
inference is the only one), which takes one collecting run and one more for channel
attention, a few more for MST++'s chain of attention layers.

Shapes: maps are ``(1, C, h, w)`` (tiles run one at a time); a pooled mean is
``(1, C, 1, 1)``.
"""

from __future__ import annotations

import contextlib
import contextvars
import threading

import numpy as np
import torch

from mehs.errors import InputError
from mehs.ssr.tiling_blend import owned_cells

def compiling() -> bool:
    """Whether ``torch.compile`` (dynamo) is tracing this call."""
    compiler = getattr(torch, "compiler", None)
    return bool(compiler is not None and hasattr(compiler, "is_compiling")
                and compiler.is_compiling())


class _Scoped:
    """A value set for a context (a ``ContextVar``: per thread and task) that a compiled
    graph reads as its default while no context anywhere has set it.

    ``torch.compile`` (dynamo) cannot trace ``ContextVar.get``: every layer reading one
    broke the compiled graph there, although outside tiled inference and the probes none
    is ever set. While dynamo traces, a process-wide count of the contexts that set it
    (an attribute dynamo guards on) stands in for the read when it is 0: the common case
    compiles to one graph, and a context entered later recompiles. Anywhere else, and
    while some context (in any thread) has set it, the ``ContextVar`` is read: a graph
    break when compiling, and always this context's own value. The count cannot see a
    context copied inside the ``with`` that outlives it (an asyncio task started there):
    eager code in it reads its value, compiled code the default.
    """

    def __init__(self, name: str, default):
        self._var = contextvars.ContextVar(name, default=default)
        self._default = default
        self.users = 0
        self._lock = threading.Lock()

    def get(self):
        if self.users == 0 and compiling():
            return self._default
        return self._var.get()

    @contextlib.contextmanager
    def set(self, value):
        with self._lock:
            self.users += 1
        try:
            token = self._var.set(value)
            try:
                yield
            finally:
                self._var.reset(token)      # (raises if left from another Context)
        finally:
            with self._lock:
                self.users -= 1


_ACTIVE = _Scoped("mehs_image_means", None)            # the ImageMeans in use
_DETACHED = _Scoped("mehs_statistics_detached", False)
_PLAIN = _Scoped("mehs_plain_graph", False)


def pooled_mean(module: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``x.mean(dim=(2, 3), keepdim=True)``, or the image-wide mean inside :class:`ImageMeans`."""
    ctx = _ACTIVE.get()
    m = None if ctx is None else ctx.statistic(module, (x,), _channel_sums)
    if m is None:
        m = x.mean(dim=(2, 3), keepdim=True)
        return m.detach() if _DETACHED.get() else m
    return m.view(1, -1, 1, 1).to(dtype=x.dtype, device=x.device)


def image_statistic(module: torch.nn.Module, maps: tuple[torch.Tensor, ...],
                    reduce, compared=None) -> torch.Tensor | None:
    """The image-wide mean over pixels of ``reduce``, or None: use the tile's (or image's) own.

    ``maps``: ``(1, C_i, h, w)`` feature maps of one layer call, of one size;
    ``reduce(*parts)`` sums a statistic over the pixels of the parts of them (``(C_i, h',
    w')`` views), as a tensor of any fixed shape. Inside :class:`ImageMeans` the part a
    tile owns is summed, and from the second run over the tiles on, the image-wide mean
    (the sum over the image / its pixels, float32) of the previous run is returned.
    Outside it, and in the first run, None: the layer computes its statistic from its
    own input, as without tiles. Layers whose global operation is such a mean (the
    spectral-wise attention of :mod:`mehs.ssr.net.mstpp2022`: channel Gram matrix and
    norms over all pixels) call this, and declare ``image_statistics = True``;
    :func:`pooled_mean` is one.

    ``compared(mean) -> tensor``: what of the statistic decides that the runs over the
    tiles have settled (:meth:`ImageMeans.finish`), if not the mean itself relative to
    its largest value: a quantity on a fixed scale, whose absolute change is compared
    (the attention's cosine similarities, which its Gram matrix and norms move together).
    """
    ctx = _ACTIVE.get()
    return None if ctx is None else ctx.statistic(module, tuple(maps), reduce, compared)


def statistics_detached() -> bool:
    """True inside :func:`detached_statistics`: a layer's global statistic leaves autograd."""
    return _DETACHED.get()


@contextlib.contextmanager
def detached_statistics():
    """Context: global statistics (:func:`pooled_mean`, and layers that ask
    :func:`statistics_detached`) are detached from autograd, so that a gradient
    probe (:func:`mehs.ssr.tiling_probes.torch_receptive_radius`) measures the
    network's local field only."""
    with _DETACHED.set(True):
        yield


def plain_graph_wanted() -> bool:
    """True inside :func:`plain_graph`."""
    return _PLAIN.get()


@contextlib.contextmanager
def plain_graph():
    """Context: layers build the graph they build for training (stock operators, no
    ``out=`` writes into preallocated maps, no strips) although autograd is off.
    Forward-mode differentiation (the field probe's Jacobian-vector product,
    :func:`mehs.ssr.tiling_probes.torch_receptive_radius`) has no derivative for
    ``out=`` operators, and needs no autograd graph."""
    with _PLAIN.set(True):
        yield


def _channel_sums(part: torch.Tensor) -> torch.Tensor:
    # float32 at least: a half-float map's sum over a 300² part overflows to inf
    return part.sum(dim=(1, 2), dtype=torch.promote_types(part.dtype, torch.float32))


class PoolingsCollected(Exception):
    """Raised out of a collecting forward once its last pooling is summed (see :meth:`ImageMeans.enter`)."""


class ImageMeans:
    """Image-wide means of every :func:`pooled_mean` layer, assembled from tiles.

    Use :meth:`active` around the tiles' runs, :meth:`enter` before each tile, and
    :meth:`finish` after each full run over the image. ``multiple``: the network's calls
    are reflect-padded to multiples of it (:mod:`mehs.ssr.tiling_pad`), so a tile's pooled
    maps cover its length rounded up to it.
    """

    def __init__(self, multiple: int = 1) -> None:
        self._multiple = max(1, int(multiple))
        # keyed by (layer, its n-th call in one forward): a layer called twice pools twice
        self._sums: dict[tuple, torch.Tensor] = {}
        self._counts: dict[tuple, int] = {}
        # pixels per cell of each layer call's map, per axis (see _owned)
        self._cell: dict[tuple, int] = {}
        # what of a statistic the runs' changes compare (see finish)
        self._compared: dict[tuple, object] = {}
        self._means: dict[tuple, torch.Tensor] | None = None
        self._tile: tuple | None = None
        self._calls: dict[torch.nn.Module, int] = {}
        self._last: tuple | None = None       # the last pooling of a forward, once known
        self._previous: tuple | None = None
        self._stop = False
        # the means handed out come from a collection that stopped at a learned last
        # pooling (:meth:`learn_last`): a pooling it never reached costs one more run,
        # not an error; and whether a run met such a pooling
        self._partial = False
        self._stopped = False
        self._missing = False
        self._past_last = False      # this forward has passed the learned last pooling

    @contextlib.contextmanager
    def active(self):
        with _ACTIVE.set(self):
            yield self

    def enter(self, y: tuple[int, int], x: tuple[int, int], own_y: tuple[int, int],
              own_x: tuple[int, int], last_y: bool, last_x: bool, *,
              stop_early: bool = False) -> None:
        """The next network call is the tile spanning rows ``y`` and columns ``x``
        (``(start, end)``, image pixels); it owns rows ``own_y`` and columns ``own_x``,
        to the end of the padded image where ``last_y`` / ``last_x``.

        ``stop_early``: once the last pooling of a forward is known (after one whole
        forward), :class:`PoolingsCollected` is raised right after it: a collecting run
        needs nothing after it (the paper network's heads: 45 % of its forward).
        """
        if self._last is None and self._calls:
            self._last = self._previous
        self._tile = (y, x, own_y, own_x, last_y, last_x)
        self._calls = {}
        self._stop = stop_early
        self._past_last = False

    def collected(self) -> list[tuple]:
        """The statistics (layer, call) the last finished run handed out means for."""
        return list(self._means or {})

    def learn_last(self, run) -> None:
        """Learn the last pooling of a forward from ``run()``, a forward on a small crop
        (its poolings are neither collected nor handed image means).

        Then every tile of a collecting run stops after it, the first one included
        (before, the first tile ran whole to find it: a tile's basis branches, ~15 %
        of a tiled paper network's time). A network whose small forwards pool in
        another order than its tiles' only costs one more run: a pooling the
        collecting run stopped before is given the tile's own mean in the next run,
        which collects it, and then one more run follows.
        """
        if self._tile is not None or self._means is not None:
            raise RuntimeError("learn_last runs before the collecting run")
        self._calls, self._previous = {}, None
        run()
        if self._previous is not None:
            self._last = self._previous
        self._calls = {}

    # run as written under torch.compile: its bookkeeping (a count per module, the
    # collected sums) is Python state that dynamo recompiled for at every call, up to
    # its recompile limit
    @torch.compiler.disable
    def statistic(self, module: torch.nn.Module, maps: tuple[torch.Tensor, ...],
                  reduce, compared=None) -> torch.Tensor | None:
        """See :func:`image_statistic`: collect the owned part of this call's statistic;
        the previous run's image-wide mean, or None (the tile's own)."""
        k = self._calls.get(module, 0)
        self._calls[module] = k + 1
        key = self._previous = (module, k)
        if key == self._last:
            self._past_last = True
        if compared is not None:
            self._compared[key] = compared
        if self._tile is not None:
            self._collect(key, maps, reduce)
            if self._stop and key == self._last:
                self._stopped = True
                raise PoolingsCollected
        if self._means is not None:
            m = self._means.get(key)
            if m is None and self._partial and self._past_last:
                # after where the collecting run stopped (see learn_last): this run
                # collects it; a pooling missing before that point ran in some tiles
                # only, which image-wide means cannot serve
                self._missing = True
                return None
            if m is None:
                raise InputError(f"a global pooling ({type(module).__name__}, call {k + 1}) "
                                 "ran that the collecting run did not see; image-wide means "
                                 "need every tile to run the same layers")
            return m
        return None

    def _collect(self, key: tuple, maps: tuple[torch.Tensor, ...], reduce) -> None:
        (y0, y1), (x0, x1), (oy0, oy1), (ox0, ox1), last_y, last_x = self._tile
        x = maps[0]
        if (x.dim() != 4 or x.shape[0] != 1
                or any(m.dim() != 4 or m.shape[0] != 1 or m.shape[2:] != x.shape[2:]
                       for m in maps)):
            raise InputError("image-wide means need (1, C, h, w) features of one size, got "
                             + ", ".join(str(tuple(m.shape)) for m in maps))
        rows = self._owned(key, 0, y1 - y0, int(x.shape[2]), oy0 - y0, oy1 - y0, last_y)
        cols = self._owned(key, 1, x1 - x0, int(x.shape[3]), ox0 - x0, ox1 - x0, last_x)
        parts = [m[0, :, rows[0]:rows[1], cols[0]:cols[1]] for m in maps]
        # float32 sums (torch sums in cascade: ~1e-7 relative) added up in float64 on the
        # CPU (a float64 sum cast the whole feature map first: +90 MB at 1024×512; Apple's
        # MPS devices have no float64)
        with torch.no_grad():
            s = reduce(*parts).to(device="cpu", dtype=torch.float64)
        n = parts[0].shape[1] * parts[0].shape[2]
        if key in self._sums:
            self._sums[key] += s
            self._counts[key] += n
        else:
            self._sums[key] = s
            self._counts[key] = n

    def _owned(self, key: tuple, axis: int, n: int, m: int, lo: int, hi: int,
               last: bool) -> tuple[int, int]:
        """The cells of an ``m``-cell map of an ``n``-pixel tile axis that the tile owns.

        The map covers the tile padded up to the pooling grid, by the tiling
        (``multiple``) or by the network itself: a 42-row last tile padded to 48 pools
        to 6 cells of 8 rows, which ceil(42 / 6) = 7 would misplace. A network that pads
        inside (the FC-DenseNet to 2**depth, MST++ to max(8, 2**levels)) does not say
        so, so a layer's cell size is learnt from the tiles before an axis's last, which
        need no padding and whose cells are exact (the first tile along an axis with
        several is one).
        """
        k = self._multiple
        span = -(-n // k) * k
        cells = owned_cells(span, m, lo, hi, last,
                            cell=self._cell.get((key, axis)) if last else None)
        if not last:
            self._cell[(key, axis)] = span // m
        return cells

    def finish(self) -> float:
        """End a run over the image: its sums become the means handed out next.

        Returns the largest change of any statistic since the previous run, relative to
        that layer's largest (``inf`` after the first run). A layer may say what of its
        statistic is compared (``compared`` of :func:`image_statistic`).
        """
        if not self._sums:
            raise InputError("no global pooling ran: nothing to make image-wide")
        new = {k: (v / self._counts[k]).to(torch.float32)
               for k, v in self._sums.items()}
        change = float("inf")
        if self._means is not None and not self._missing:
            change = 0.0
            for k, m in new.items():
                old = self._means.get(k)
                if old is None:
                    change = float("inf")
                    break
                f = self._compared.get(k)
                if f is not None:
                    # already on a fixed scale (cosines): compared as they are
                    m, old, scale = f(m), f(old), 1.0
                else:
                    scale = float(m.abs().max()) or 1.0
                d = float((m - old).abs().max()) / scale
                if not np.isfinite(d):
                    raise InputError(f"image-wide statistics of {type(k[0]).__name__} (call "
                                     f"{k[1] + 1}) are not finite: the tiles' features "
                                     "overflow or hold NaN; use tiling statistics 'tile' "
                                     "or 'off'")
                change = max(change, d)
        self._means, self._sums, self._counts, self._tile = new, {}, {}, None
        self._partial, self._stopped, self._missing = self._stopped, False, False
        self._stop = False
        return change
