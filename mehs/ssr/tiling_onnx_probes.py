"""The tiling grid and margin of an ONNX graph, measured (issue 16, session 26).

Until session 26 every ONNX model was tiled with a 64-pixel margin on a 32-pixel grid:
a graph with a wider field (MST++'s is 112 px) or a deeper pooling stack was tiled
off what its tiles need, and differed from whole-image inference near the seams without
a word. Both are now measured once per graph file (kept in the probe cache, keyed by
the file's bytes):

- :func:`onnx_strides` — the grid, as :mod:`mehs.ssr.tiling_grid` reads it for torch,
  from the output shapes onnxruntime's profiler records for every node over the three
  probe runs. (``onnx.shape_inference`` cannot do it: the size a graph pads to inside is
  computed, and its maps' sizes are unknown to it.)
- :func:`onnx_margin` — the margin, by finite differences, as tiling cuts: a strip's
  input on one side of an aligned cut is replaced, and the farthest output that moves
  on the other side is how far a tile's missing context reaches into it (the sum of
  everything cut off, not one block's share), on inputs in [0, 1) and on inputs whose
  brightness spans 0.1–100 (a path open only on bright pixels is then open). A graph's
  global average poolings would spread the change over every output; they run on given means
  (:class:`mehs.ssr.tiling_onnx.OnnxImageMeans`, the same in both runs), so what is
  measured is the field of the rest. An output moved by less than float rounding is
  not counted: tiles are then equal to that rounding. A field that fills the largest
  probe the memory budget allows gives a lower bound with a warning
  (:class:`~mehs.ssr.tiling_probes.FieldWiderThanBudget`), one that fills a
  :data:`MAX_PROBE` probe a global operation (:data:`GLOBAL_MARGIN`).

Without the ``onnx`` package, or where the grid probe cannot run, the defaults of
:mod:`mehs.ssr.tiling` (64 px on a grid of 32) are used, with a warning.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from mehs.ssr.tiling_grid import PROBE_SHAPE, probe_shape, shapes, strides_of_runs
from mehs.ssr.tiling_probes import GLOBAL_MARGIN, FieldWiderThanBudget

#: The longest margin probe (fields of up to ~1000 px: the full paper network's ~400).
MAX_PROBE = 2048
#: The first margin probe's length, and the strips' width (a field's reach along one
#: axis does not need the other's extent).
FIRST_PROBE, STRIP = 256, 64


def _input(model, rgb: np.ndarray) -> dict:
    return {model.input_name: model._graph_input(np.ascontiguousarray(rgb, dtype=np.float32))}


def onnx_strides(model, *, shape: tuple[int, int] = PROBE_SHAPE) -> set[int]:
    """Strides ``s ≥ 2`` of the down-sampled maps an :class:`~mehs.ssr.models.OnnxModel`'s
    graph computes (:mod:`mehs.ssr.tiling_grid`). ``shape`` must be a multiple of the
    model's size multiple (no padding blurs the maps), and even.

    The shapes are those onnxruntime's profiler records for every node it runs, on the
    three probe sizes in one session: the graph runs as it always does, in the memory of
    one inference, contrib operators (``com.microsoft::FusedConv`` of a graph onnxruntime
    optimised) included. (``Shape`` nodes on every value kept every value alive at once:
    10.8 GB for MST++ full; and values ``onnx`` could not type, behind a contrib
    operator, were left out.)
    """
    import json
    import os
    import tempfile

    import onnx
    import onnxruntime as ort

    from mehs.ssr.onnx_model import onnx_session_options

    proto = onnx.load(str(model.path))
    # the profiler names each node's events after it: names must be unique
    for i, node in enumerate(proto.graph.node):
        node.name = f"mehs_node_{i}"
    so = onnx_session_options()
    so.enable_profiling = True
    sizes = shapes(shape)
    rng = np.random.default_rng(0x6D656873)
    with tempfile.TemporaryDirectory(prefix="mehs-grid-") as tmp:
        so.profile_file_prefix = os.path.join(tmp, "profile")
        session = ort.InferenceSession(proto.SerializeToString(), sess_options=so,
                                       providers=model.session.get_providers())
        del proto
        out = [model.output_name]
        for size in sizes:
            session.run(out, _input(model, rng.random((*size, 3), dtype=np.float32)))
        with open(session.end_profiling()) as f:
            events = json.load(f)
    return strides_of_runs(_profiled_runs(events, len(sizes)), sizes)


def _profiled_runs(events: list, n: int) -> list[dict]:
    """Per run (in order), the output shapes of every node the profiler saw: keyed by
    (node, its k-th run within the run, output index)."""
    runs = sorted((e for e in events if e.get("cat") == "Session" and e.get("name") == "model_run"),
                  key=lambda e: e["ts"])
    if len(runs) != n:
        raise RuntimeError(f"the profiler recorded {len(runs)} runs, not {n}")
    bounds = [(r["ts"], r["ts"] + r["dur"]) for r in runs]
    out: list[dict] = [{} for _ in range(n)]
    count: list[dict] = [{} for _ in range(n)]
    for e in sorted((e for e in events if e.get("cat") == "Node"
                     and str(e.get("name", "")).endswith("_kernel_time")), key=lambda e: e["ts"]):
        r = next((i for i, (t0, t1) in enumerate(bounds) if t0 <= e["ts"] <= t1), None)
        if r is None:
            continue
        name = e["name"]
        k = count[r][name] = count[r].get(name, -1) + 1
        for i, typed in enumerate(e.get("args", {}).get("output_type_shape", [])):
            dims = next(iter(typed.values()), None) if isinstance(typed, dict) else None
            if isinstance(dims, list) and all(isinstance(d, int) for d in dims):
                out[r][(name, k, i)] = tuple(dims)
    return out


def onnx_grid(model) -> int:
    """Tile grid of an ONNX model: the least common multiple of 8, its size multiple and
    :func:`onnx_strides`. (The probe is not shrunk to a memory budget: on a smaller one
    a network that pads to its grid blurs its maps' sizes, and the grid read off them
    was wrong, and cached.)"""
    from mehs.ssr.tiling_pad import size_multiple

    k = size_multiple(model)
    return math.lcm(8, k, *onnx_strides(model, shape=probe_shape(None, k)))


def _runner(model):
    """``(run, close)``: ``run(rgb)`` is the model's output with its global average
    poolings on means given once (from the first image it sees); ``close()`` lets the
    rebuilt graph go. The graph is rebuilt on a copy of the model: the model's own
    session stays in place for other threads."""
    import copy

    from mehs.errors import InputError
    from mehs.ssr.tiling_onnx import OPEN_END, OnnxImageMeans, _finite_means

    model = copy.copy(model)
    try:
        state = OnnxImageMeans(model)
    except InputError:
        # a graph whose poolings cannot take given means: they spread the change over
        # every output, and the field reads as global (so do its tiles' statistics)
        return model._predict_whole, lambda: None
    if not state.k:
        return model._predict_whole, lambda: None
    given: list = []
    whole = np.array([0, OPEN_END, 0, OPEN_END], np.int64)

    def run(rgb: np.ndarray) -> np.ndarray:
        if not given:
            sums, counts = [None] * state.k, [0] * state.k
            state.run(rgb, whole, (True, True), None, sums, counts, spectra=False)
            given.extend(_finite_means(sums, counts))
        return state.run(rgb, whole, (True, True), given, [None] * state.k, [0] * state.k)
    return run, state.restore


def _probe_input(rng, shape, hdr: bool) -> np.ndarray:
    """Uniform [0, 1), or (``hdr``) that times a log-uniform brightness from 0.1 to 100
    per pixel: a path that opens only on bright (or dark) pixels is open somewhere."""
    x = rng.random(shape, dtype=np.float32)
    if hdr:
        x *= (10.0 ** rng.uniform(-1.0, 2.0, shape[:2] + (1,))).astype(np.float32)
    return x


def _reach(run, length: int, side: int, a: int, rng, axis: int,
           hdr: bool = False) -> int | None:
    """The margin along ``axis`` (1: columns, 0: rows) that a ``side``-wide strip of
    ``length`` pixels shows: the input on either side of an aligned cut ``c`` is
    replaced, and the outputs that move on the far side tell how far a tile's cut-off
    context reaches into it (all rows of the strip together). None where they reach the
    strip's end. ``hdr``: inputs of :func:`_probe_input`."""
    shape = (side, length, 3) if axis == 1 else (length, side, 3)
    x = _probe_input(rng, shape, hdr)
    c = length // 2 // a * a
    y0 = run(x)
    far = []
    for before in (True, False):
        moved = x.copy()
        cut = (slice(None), slice(None, c) if before else slice(c, None))
        cut = cut if axis == 1 else cut[::-1]
        moved[cut] = _probe_input(rng, moved[cut].shape, hdr)
        # NaN or inf counts as moved: the probe cannot tell, and a wider margin is safe
        changed = ~(run(moved) == y0).all(-1).all(1 - axis)
        idx = np.nonzero(changed[c:] if before else changed[:c])[0]
        if before:
            if changed[-1]:
                return None
            far.append(int(idx.max()) + 1 if idx.size else 0)   # outputs c … c + reach − 1
        else:
            if changed[0]:
                return None
            far.append(c - int(idx.min()) if idx.size else 0)
    return max(-(-f // a) * a for f in far)


def onnx_margin(model, align: int, *, max_bytes: int | None = None,
                bytes_per_pixel: float | None = None) -> int:
    """Tile margin of an ONNX model on the grid ``align``, by finite differences (see the
    module doc): strips :data:`STRIP` pixels wide and 256, 512, … :data:`MAX_PROBE` long,
    along each axis. ``max_bytes``/``bytes_per_pixel``: a longer strip runs only if two
    of its images' worth of memory fit; else :class:`FieldWiderThanBudget` (half the
    longest strip the field filled, on the grid: a lower bound)."""
    from mehs.ssr.tiling_pad import size_multiple

    a = max(1, int(align))
    step = math.lcm(a, size_multiple(model))
    side = -(-max(STRIP, 2 * step) // step) * step
    length = -(-max(FIRST_PROBE, 4 * step) // step) * step
    rng = np.random.default_rng(0x6D656873)
    run, close = _runner(model)
    filled = None
    try:
        while True:
            need = None if bytes_per_pixel is None else 2.0 * bytes_per_pixel * length * side
            # the first strip always runs (smaller than any tile worth a margin)
            if (filled is not None and max_bytes is not None and need is not None
                    and need > max_bytes):
                raise FieldWiderThanBudget(-(-(filled // 2) // a) * a, filled, int(need))
            margins = []
            for axis in (1, 0):
                for hdr in (False, True):
                    # the first strip the field fills decides: a longer one comes next
                    # (a global operation fills them all: 4 runs a length, not 12)
                    margins.append(_reach(run, length, side, a, rng, axis, hdr))
                    if margins[-1] is None:
                        break
                if margins[-1] is None:
                    break
            if None not in margins:
                return max(margins)
            filled = length
            if length >= MAX_PROBE:
                return GLOBAL_MARGIN
            length *= 2
    finally:
        close()


def _external_files(path) -> list:
    """The files an ONNX model keeps its external-data tensors in (their bytes are the
    weights, which the margin depends on)."""
    from pathlib import Path

    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    found = set()
    graphs = [proto.graph]
    while graphs:
        g = graphs.pop()
        for t in g.initializer:
            if t.data_location == onnx.TensorProto.EXTERNAL:
                for e in t.external_data:
                    if e.key == "location":
                        found.add(e.value)
        for n in g.node:
            for a in n.attribute:
                graphs.extend([a.g] if a.HasField("g") else [])
                graphs.extend(a.graphs)
    return [Path(path).parent / f for f in sorted(found)]


def onnx_file_key(model) -> str:
    """The probe-cache key of an ONNX model: its file's bytes and its external data's,
    the output it is read from, its size multiple and the probes' source (an edit
    measures again)."""
    from pathlib import Path

    import mehs.ssr.tiling_grid
    import mehs.ssr.tiling_onnx
    import mehs.ssr.tiling_onnx_graph
    import mehs.ssr.tiling_probes
    from mehs.ssr.tiling_pad import size_multiple

    h = hashlib.sha256()
    files = [model.path]
    try:
        files += _external_files(model.path)
    except ImportError:
        pass                  # without onnx nothing is measured, so nothing is stored
    for name in files:
        h.update(f"\0{Path(name).name}\0".encode())
        with open(name, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    h.update(f"\0k={size_multiple(model)}\0out={getattr(model, 'output_name', '')}\0"
             f"layout={getattr(model, 'layout', '')}\0".encode())
    for mod in (mehs.ssr.tiling_grid, mehs.ssr.tiling_onnx, mehs.ssr.tiling_onnx_graph,
                mehs.ssr.tiling_probes):
        h.update(hashlib.sha256(Path(mod.__file__).read_bytes()).digest())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()


def onnx_tiling_probes(model, memory, opts: dict) -> dict:
    """The ``probes`` of :func:`mehs.ssr.tiling.tiled_network_call` for an ONNX model:
    ``memory`` as given, the grid (:func:`onnx_grid`) and the margin (:func:`onnx_margin`,
    a lower bound with a warning where the budget cannot hold the probe that contains
    the field), both kept in the probe cache by the graph file's bytes."""
    import warnings

    from mehs.errors import first_line
    from mehs.ssr.probe_cache import ProbeStore
    from mehs.ssr.tiling import ONNX_DEFAULT_ALIGN, ONNX_DEFAULT_MARGIN, probe_budget
    from mehs.ssr.tiling_probes import margin_or_bound, once, within_known_bound

    store = ProbeStore.for_onnx(model)
    cached = model.__dict__.get("_tiling_probe", {})
    if cached.pop("margin_bound", False):
        cached.pop("margin", None)      # a lower bound is one call's answer only

    def bpp() -> float | None:
        # measured only: a bytes_per_pixel given for planning the tiles may be a fiction
        v = model.__dict__.get("_tiling_probe", {}).get("bytes_per_pixel")
        return None if v is None else float(v)

    def unmeasured(what: str, default: int, why: str) -> int:
        warnings.warn(f"{model.name}: its tiling {what} cannot be measured ({why}); {default} "
                      f"px is used, which may not cover it (model.tiling = {{\"{what}\": …}})",
                      RuntimeWarning, stacklevel=4)
        return default

    def align() -> int:
        v = store.get("align")
        if v is None:
            try:
                v = onnx_grid(model)
            except ImportError:
                return unmeasured("align", ONNX_DEFAULT_ALIGN,
                                  'the onnx package is missing: pip install "mehs[onnx]"')
            except Exception as exc:    # noqa: BLE001 - onnxruntime's own types
                return unmeasured("align", ONNX_DEFAULT_ALIGN,
                                  f"the grid probe's run failed: {first_line(exc)}")
            store.put("align", v)
        return v

    align = once(align)

    def margin() -> int:
        v = store.get("margin")
        if v is not None:
            return v
        b = probe_budget(opts)
        try:
            v = within_known_bound(store, b, lambda: onnx_margin(
                model, align(), max_bytes=b, bytes_per_pixel=bpp()))
        except ImportError:
            return unmeasured("margin", ONNX_DEFAULT_MARGIN,
                              'the onnx package is missing: pip install "mehs[onnx]"')
        finally:
            # the arena keeps the probes' peak, which the tiles' budget would lose
            release = getattr(model, "release_memory", None)
            if release is not None:
                release()
        store.put("margin", v)
        return v

    return {"bytes_per_pixel": memory, "margin": margin_or_bound(model, margin),
            "align": align}
