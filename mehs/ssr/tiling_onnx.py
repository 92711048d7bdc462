"""Image-wide global-pooling means for tiled ONNX inference (issue 16).

An ONNX graph's global average poolings (squeeze-and-excitation: the channel
attention of the paper's network, exported by ``mehs train-ssr``) see only a tile's
pixels when the graph runs tile by tile, so tiled output differs from whole-image
inference. As for torch networks (:mod:`mehs.ssr.tiling_global`), the means can be
assembled from the tiles, once the graph lets them in and out. :func:`means_graph`
rebuilds the graph with the ``onnx`` package so that every global average pooling
(``GlobalAveragePool``, or ``ReduceMean`` over axes 2 and 3 keeping them)

- hands on a mean given as an input (``mehs_mean_<k>``, taken when ``mehs_given``
  is true) instead of its own, and
- outputs its feature map's sum over the part of the tile the tile owns
  (``mehs_sum_<k>``, float32 ``(1, C)``) and the map's shape (``mehs_map_<k>``): the
  owned span comes in tile pixels (``mehs_owned``: rows ``[y0, y1)``, columns
  ``[x0, x1)``) and the graph divides it by each map's pixel size: ``ceil(tile / map)``,
  or the size given in ``mehs_cells`` (per pooling and axis; 0: not given), which an
  image's last tile gets from the tiles before it when the graph pads it inside.

:func:`predict_tiled_onnx_image_means` then runs the tiles as
:func:`mehs.ssr.tiling_global.predict_tiled_image_means` does: a collecting run, then
runs with the collected means until the means given and measured agree.

Whether a graph's only global operations are such poolings cannot be read off a graph
in general (a reduction over a reshaped image, an attention matrix, a ``GlobalMaxPool``).
So it is measured, once per model: a probe image, tiled with image-wide means on the
model's tiling grid and margin, must equal its whole-image inference to
:data:`PROBE_TOL` of its range (all but 0.1 % of its values: see
:func:`probe_image_means`). Otherwise ``statistics="auto"`` gives each tile its own
means, and ``"image"`` refuses.

The rebuilt graph replaces the model's session (one onnxruntime arena, not two); a
plain run feeds ``mehs_given = false`` and asks for the spectra only, and the pooling
then hands on its own mean through a ``Where``: the same numbers as the original graph.
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

from mehs.errors import InputError
from mehs.ssr.tiling_blend import TilingPlan, owned_cells, predict_tiled
from mehs.ssr.tiling_check import CHECK_TOL, probe_image, relative_difference
from mehs.ssr.tiling_global import (IMAGE_MEANS_TOL, go_on, owned_spans, tile_windows,
                                    warn_tiles_differ, warn_unsettled)
from mehs.ssr.tiling_probes import GLOBAL_MARGIN
from mehs.ssr.tiling_onnx_graph import _CELLS, _GIVEN, _OWNED, means_graph, pruned_graph

#: Whole-image agreement a probe of the rebuilt graph must show (relative to the range),
#: by all but a 1e-3 share of its values (:func:`mehs.ssr.tiling_check.relative_difference`).
PROBE_TOL = CHECK_TOL
#: Owned-span end of an image's last tile, which runs on into the network's padding
#: (``Slice`` clamps it to the map).
OPEN_END = 2 ** 40


class OnnxImageMeans:
    """An :class:`~mehs.ssr.models.OnnxModel` switched to its means graph.

    Construction rebuilds the graph (:func:`means_graph`) and replaces the model's
    session with it; :attr:`k` is the number of poolings (0: nothing was changed).
    """

    def __init__(self, model):
        import onnx
        import onnxruntime as ort

        from mehs.ssr.models import onnx_session_options

        self.model = model
        # pixels per cell of each pooling's map, per axis, from tiles that need no padding
        self.cells: dict[tuple[int, int], int] = {}
        proto = onnx.load(str(model.path))
        graph, self.k = means_graph(proto, model.input_name, model.layout)
        if not self.k:
            return
        old = model.session
        # the output the model reads its spectra from (not the graph's first: it may
        # have several, mehs.ssr.onnx_model)
        self.spectra = model.output_name
        self.extras = [f"mehs_{what}_{i}" for i in range(self.k) for what in ("sum", "map")]
        # both sessions draw on one process-wide arena: two arenas would each keep
        # their peak
        _register_shared_arena(ort)
        so = onnx_session_options()
        so.add_session_config_entry("session.use_env_allocators", "1")
        providers = old.get_providers()
        try:
            session = ort.InferenceSession(graph.SerializeToString(), sess_options=so,
                                           providers=providers)
            # the collecting run needs the graph up to the last pooling only (onnxruntime
            # runs every node of a session, asked for its outputs or not)
            collect = pruned_graph(graph, self.extras)
            self.collect = None if collect is None else ort.InferenceSession(
                collect.SerializeToString(), sess_options=so, providers=providers)
        except Exception as exc:  # onnxruntime raises its own exception types
            raise InputError(f"{model.name}: its graph cannot take image-wide pooling means "
                             f"({exc})", model.path) from None
        types = {i.name: i.type for i in session.get_inputs()}
        self.dtype = np.float16 if "float16" in types.get("mehs_mean_0", "") else np.float32
        self._old = (old, model._run_outputs, model._run_feeds)
        model.session = session
        model._run_outputs = [self.spectra]
        model._run_feeds = self.feeds(None, None)

    def keep(self) -> None:
        """Keep the rebuilt graph (the original session and its arena are released)."""
        self._old = None

    def restore(self) -> None:
        """Put the original graph back."""
        if self.k and self._old is not None:
            self.model.session, self.model._run_outputs, self.model._run_feeds = self._old
            self._old = None

    def feeds(self, means: list[np.ndarray] | None, owned: np.ndarray | None,
              cells: np.ndarray | None = None) -> dict:
        none = np.zeros((1, 1, 1, 1), dtype=self.dtype)
        return {_GIVEN: np.array(means is not None),
                _OWNED: np.zeros(4, np.int64) if owned is None else owned,
                _CELLS: np.zeros(2 * self.k, np.int64) if cells is None else cells,
                **{f"mehs_mean_{i}": none if means is None else means[i].astype(self.dtype)
                   for i in range(self.k)}}

    def run(self, rgb: np.ndarray, owned: np.ndarray, last: tuple[bool, bool],
            means: list[np.ndarray] | None, sums: list, counts: list,
            spectra: bool = True) -> np.ndarray | None:
        """One tile: adds each pooling's owned sum and pixel count into ``sums``/``counts``.

        A graph with a size multiple gets the tile reflect-padded to it (the owned span's
        open end then runs on into that padding, as the whole padded image's does); its
        pooled maps' cells are sized on the padded tile. A graph that pads inside (to its
        pooling grid: the mehs networks) pools an off-grid last tile over its own padding:
        its cells are those learnt from the tiles before it (``cells``), which need none.
        """
        from mehs.ssr.tiling_pad import pad_to_multiple, size_multiple

        m = self.model
        x = pad_to_multiple(rgb, size_multiple(m))
        learnt = np.array([self.cells.get((i, a), 0) if last[a] else 0
                           for i in range(self.k) for a in (0, 1)], np.int64)
        feeds = {m.input_name: m._graph_input(x), **self.feeds(means, owned, learnt)}
        session = m.session if spectra or self.collect is None else self.collect
        if session is not m.session:
            names = {i.name for i in session.get_inputs()}
            feeds = {k: v for k, v in feeds.items() if k in names}
        outs = session.run(([self.spectra] if spectra else []) + self.extras, feeds)
        tile = rgb.shape[:2]
        extra = outs[1:] if spectra else outs
        for i in range(self.k):
            s, shape = np.asarray(extra[2 * i], np.float64), np.asarray(extra[2 * i + 1])
            # the maps cover the padded tile (a 42-row last tile padded to 48 pools to
            # 6 cells of 8 rows, not ceil(42 / 6) = 7): the padded length, as in the graph
            cells = []
            for a in (0, 1):
                n, n_map = x.shape[a], int(shape[2 + a])
                cells.append(owned_cells(n, n_map, int(owned[2 * a]), int(owned[2 * a + 1]),
                                         last[a], m.name, cell=int(learnt[2 * i + a])))
                if not last[a]:
                    self.cells[(i, a)] = n // n_map
            n = (cells[0][1] - cells[0][0]) * (cells[1][1] - cells[1][0])
            sums[i] = s.reshape(-1) if sums[i] is None else sums[i] + s.reshape(-1)
            counts[i] += n
        return m._spectra(outs[0], x.shape[:2])[:tile[0], :tile[1]] if spectra else None


_ARENA = []


def _register_shared_arena(ort) -> None:
    """Register onnxruntime's process-wide CPU arena once (``session.use_env_allocators``)."""
    if not _ARENA:
        info = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0,
                                 ort.OrtMemType.DEFAULT)
        ort.create_and_register_allocator(info, None)
        _ARENA.append(info)


def predict_tiled_onnx_image_means(means: OnnxImageMeans, rgb: np.ndarray, plan: TilingPlan,
                                   *, tol: float = IMAGE_MEANS_TOL,
                                   max_runs: int | None = None,
                                   record: dict | None = None) -> np.ndarray:
    """:func:`mehs.ssr.tiling_blend.predict_tiled` of the model behind ``means`` with
    image-wide pooling means; float32 ``(H, W, B)``. ``record`` as
    :func:`mehs.ssr.tiling_global.predict_tiled_image_means`."""
    record = {} if record is None else record
    model = means.model
    if plan.tile is None:
        return model._predict_whole(rgb)
    if max_runs is not None and max_runs < 2:
        raise InputError(f"image-wide means need at least 2 runs over the tiles, got {max_runs}")
    h, w = rgb.shape[:2]
    rows, cols = owned_spans(h, plan.tile, plan), owned_spans(w, plan.width, plan)

    def span(y0: int, x0: int) -> tuple[np.ndarray, tuple[bool, bool]]:
        ry, rx = rows[y0], cols[x0]
        return (np.array([ry[0] - y0, OPEN_END if ry[2] else ry[1] - y0,
                          rx[0] - x0, OPEN_END if rx[2] else rx[1] - x0], np.int64),
                (ry[2], rx[2]))

    def fresh():
        return [None] * means.k, [0] * means.k

    sums, counts = fresh()
    for y0, y1, x0, x1 in tile_windows(rows, cols, plan, h, w):   # spectra not asked for
        owned, last = span(y0, x0)
        means.run(np.ascontiguousarray(rgb[y0:y1, x0:x1]), owned, last, None, sums, counts,
                  spectra=False)
    given = _finite_means(sums, counts)
    change = float("inf")
    run, before = 1, float("inf")
    while go_on(run, max_runs, means.k, change, before):
        run, before = run + 1, change
        sums, counts = fresh()
        here: dict = {}

        def on_tile(y0, y1, x0, x1):
            here["span"] = span(y0, x0)

        def fn(tile: np.ndarray) -> np.ndarray:
            owned, last = here["span"]
            return means.run(tile, owned, last, given, sums, counts)

        out = None                    # (one stitched output alive, as in tiling_global)
        out = predict_tiled(fn, rgb, plan, on_tile=on_tile)
        new = _finite_means(sums, counts)
        change = max(float(np.abs(a - b).max()) / (float(np.abs(a).max()) or 1.0)
                     for a, b in zip(new, given))
        given = new
        record.update(image_runs=run, image_means_change=change)
        if change <= tol:
            return out
    warn_unsettled(change, run)
    return out


def _finite_means(sums, counts) -> list[np.ndarray]:
    """The image-wide means of one run over the tiles, refused when not finite (as the
    torch path's :meth:`mehs.ssr.net.pooling.ImageMeans.finish`): a NaN change never
    counted as settled, so all the runs ran and the output came out NaN."""
    means = []
    for i, (s, c) in enumerate(zip(sums, counts)):
        m = (s / c).astype(np.float32).reshape(1, -1, 1, 1)
        if not np.all(np.isfinite(m)):
            raise InputError(f"image-wide statistics of pooling {i + 1} are not finite: the "
                             "tiles' features overflow or hold NaN (a NaN or inf in the "
                             "input?); use tiling statistics 'tile' or 'off'")
        means.append(m)
    return means


def probe_image_means(means: OnnxImageMeans, plan: TilingPlan) -> tuple[bool, float]:
    """Whether tiles with image-wide means equal whole-image inference on a probe.

    The probes have two tiles side by side, and two one above the other (a graph may be
    shift-equivariant along one axis only), on ``plan``'s grid, margin and blend (the
    smallest such tiles). Returns ``(agrees, max |tiled − whole| / max |whole|)``.
    """
    a = plan.align
    side = -(-(plan.overlap + a) // a) * a        # the smallest tile on the grid
    step = (side - plan.overlap) // a * a
    probe_plan = TilingPlan(side, plan.margin, plan.blend, a, side)
    diff = 0.0
    for h, w in ((side, side + step), (side + step, side)):
        rgb = probe_image(h, w)
        whole = means.model._predict_whole(rgb)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            tiled = predict_tiled_onnx_image_means(means, rgb, probe_plan)
        diff = max(diff, relative_difference(tiled, whole, overwrite=True))
        if diff == float("inf"):
            return False, diff
    return diff <= PROBE_TOL, diff


def onnx_image_means_stitcher(model) -> Callable[..., np.ndarray]:
    """The ``image_means`` of :func:`mehs.ssr.tiling.tiled_network_call` for an ONNX model.

    The first call rebuilds the graph and probes it (kept in ``model._tiling_probe``:
    ``image_means`` True/False and ``image_means_probe_diff``); a graph without global
    average poolings, or whose probe disagrees, gets each tile's own statistics, or is
    refused when ``strict``.
    """
    def stitch(fn, rgb, plan, strict):
        record = model.__dict__.setdefault("_tiling_last", {})
        probe = model.__dict__.setdefault("_tiling_probe", {})
        if "image_means" not in probe:
            probe.update(_probe_onnx_image_means(model, plan))
        if not probe["image_means"]:
            if strict:
                why = probe["image_means_why"]
                raise InputError(f"{model.name}: image-wide tiling statistics do not make its "
                                 f"tiles equal the whole image: {why}; use statistics 'tile' "
                                 "or 'off'", getattr(model, "path", None))
            if probe["image_means_poolings"] != 0 or probe.get("margin") == GLOBAL_MARGIN:
                # (a graph without poolings and with a measured field is local: exact)
                warn_tiles_differ(model, "its global operations are not average poolings "
                                         "tiles can assemble" if not probe["image_means_poolings"]
                                  else probe["image_means_why"])
            return predict_tiled(fn, rgb, plan)
        record["statistics"] = "image"
        return predict_tiled_onnx_image_means(model.__dict__["_onnx_image_means"], rgb, plan,
                                              record=record)
    return stitch


def _probe_onnx_image_means(model, plan: TilingPlan) -> dict:
    """Rebuild and probe ``model``'s graph once; what :func:`onnx_image_means_stitcher` keeps."""
    try:
        state = OnnxImageMeans(model)
    except (InputError, ImportError) as exc:     # onnx missing, or a graph it cannot rebuild
        return {"image_means": False, "image_means_poolings": None,
                "image_means_probe_diff": None, "image_means_why": str(exc)}
    if not state.k:
        return {"image_means": False, "image_means_poolings": 0, "image_means_probe_diff": None,
                "image_means_why": "it has no global average pooling (GlobalAveragePool, "
                                   "ReduceMean over axes 2 and 3)"}
    try:
        ok, diff = probe_image_means(state, plan)
        why = (None if ok else
               f"with image-wide pooling means its tiles still differ from the whole image "
               f"by {diff:.1e} of the range on a probe (other global operations, or a "
               "margin too small: model.tiling['margin'])")
    except InputError as exc:
        ok, diff, why = False, None, str(exc)
    if ok:
        state.keep()
        model.__dict__["_onnx_image_means"] = state
    else:
        state.restore()
    return {"image_means": ok, "image_means_poolings": state.k,
            "image_means_probe_diff": diff, "image_means_why": why}
