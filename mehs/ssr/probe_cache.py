"""On-disk cache of the tiling probes of mehs's own SSR networks (issue 16).

Tiled inference (:mod:`mehs.ssr.tiling`) measures a network before planning: its
memory per pixel (three small runs), its receptive-field margin (a backward
pass) and its pooling grid. On 2048×1024 images that is 0.55–0.85 s of a 9–11 s
call, in every new process. The figures depend on the architecture, never on
the weights, so they are kept in ``<cache>/tiling/<key>.json`` and read back by
later processes.

Only networks whose every module is defined in :mod:`mehs.ssr.net` (or is a
``torch.nn`` layer) are cached: their configuration is visible in the module
tree, and the key covers it — the module tree's ``repr``, every parameter's and
buffer's name, shape and dtype, the modules' ``chunk_pixels``, the device type,
the torch version and the source of every mehs module the network is built
from and of the probes themselves (an edit re-measures). A user network may
hold configuration outside its ``repr``, so it is probed in every process.

The cache folder is :func:`mehs._cache.cache_dir`'s: ``MEHS_CACHE_DIR`` if set (empty: no
cache), else ``$XDG_CACHE_HOME/mehs`` or ``~/.cache/mehs`` (a private temporary folder
where that cannot be written). A file that does not parse or
does not carry its key is ignored and rewritten; writes are atomic.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

from mehs._cache import cache_dir

#: Bumped when the meaning of a stored figure changes.
FORMAT = "mehs-tiling-probe/1"
#: What is stored, with the type each must have when read back.
_KINDS = {"memory": dict, "margin": int, "align": int,
          # a field wider than the probes a budget allows: {"needed", "lower_bound",
          # "probe"} (:class:`mehs.ssr.tiling_probes.FieldWiderThanBudget`); a budget of
          # at least "needed" bytes measures again
          "margin_bound": dict}


def _mehs_module(cls: type) -> bool:
    return cls.__module__.startswith("mehs.ssr.net")


def _torch_module(cls: type) -> bool:
    return cls.__module__.startswith("torch.nn.modules")


_NET_PACKAGE = Path(__file__).resolve().parent / "net"


def cacheable(network) -> bool:
    """Whether a torch network is mehs's own: a mehs network built only of mehs and torch
    modules (any other code could change what the probes measure unseen). Its probes
    are cached unless it carries hooks (:func:`network_key`)."""
    return _mehs_module(type(network)) and all(
        _mehs_module(type(m)) or _torch_module(type(m)) for m in network.modules())


def graph_signature(network) -> tuple:
    """What decides which inference path a network takes beyond its modules' types:
    its hooks, autocast and the plain-graph context (the plain graphs), the strips' sizes
    and the row windows of modules that stream (a model's probes measured under another
    signature describe another memory, and a hook may widen the field)."""
    from mehs.ssr.net.pooling import plain_graph_wanted
    from mehs.ssr.net.strips import autocast_state, hooked

    windows = tuple(int(m.stream_window_rows(64)) for m in network.modules()
                    if callable(getattr(m, "stream_window_rows", None)))
    chunks = tuple(getattr(m, "chunk_pixels", None) for m in network.modules())
    return (hooked(network), autocast_state(), bool(plain_graph_wanted()), chunks, windows)


def network_key(network) -> str | None:
    """The cache key of a torch network, or None when it must not be cached (see module doc)."""
    import torch

    from mehs.ssr.net.strips import hooked

    if not cacheable(network) or hooked(network):
        # (a hook turns the lean inference paths off: a hooked HSCNN-D holds its dense
        # features, 30x the streamed memory of the full preset, under the same key)
        return None
    mods = list(network.modules())
    h = hashlib.sha256()

    def add(*parts: Any) -> None:
        for p in parts:
            h.update(str(p).encode())
            h.update(b"\0")

    from mehs.ssr.net.strips import autocast_state

    # under autocast the networks run their plain graphs in lower precision: other memory
    add(FORMAT, torch.__version__, repr(network), autocast_state())
    for name, t in [*network.named_parameters(), *network.named_buffers()]:
        add(name, tuple(t.shape), t.dtype, t.device.type)
    for m in mods:
        # (a module in training mode runs other code: batch norms on batch statistics
        # take no strips, and a network probed so would store twice its eval memory)
        add(type(m).__qualname__, getattr(m, "chunk_pixels", None), m.training)
    files = {sys.modules[type(m).__module__].__file__ for m in mods if _mehs_module(type(m))}
    # the network package whole: a network's inference also runs helpers of modules that
    # define none of its layers (MST++'s strips in mstpp_lean, the strip convolutions in
    # layers), whose changes move its memory per pixel
    files |= {str(f) for f in _NET_PACKAGE.glob("*.py")}
    import mehs.ssr.net.pooling
    import mehs.ssr.tiling
    import mehs.ssr.tiling_grid
    import mehs.ssr.tiling_probes
    import mehs.ssr.tiling_torch

    # the probes, the hook that runs them, and the statistics they detach
    files |= {mehs.ssr.tiling.__file__, mehs.ssr.tiling_probes.__file__,
              mehs.ssr.tiling_grid.__file__, mehs.ssr.tiling_torch.__file__,
              mehs.ssr.net.pooling.__file__, __file__}
    for f in sorted(f for f in files if f):
        add(Path(f).name, hashlib.sha256(Path(f).read_bytes()).hexdigest())
    return h.hexdigest()


class ProbeStore:
    """The stored probes of one network (``get``/``put`` by kind: memory, margin, align).

    The key (which hashes the network's source files) is worked out at the first
    ``get`` or ``put``, so a store is free to make for every call that might need it.
    """

    def __init__(self, network, *, key=None):
        self._network = network
        self._key = key             # a callable giving the key, else network_key(network)
        self._where: tuple[Path | None, str | None] | None = None
        self._data: dict | None = None

    @classmethod
    def for_network(cls, network) -> "ProbeStore":
        return cls(network)

    @classmethod
    def for_onnx(cls, model) -> "ProbeStore":
        """The store of an ONNX model's grid and margin, keyed by its graph file's bytes
        (:func:`mehs.ssr.tiling_onnx_probes.onnx_file_key`); its memory is not stored
        (onnxruntime's arena makes it depend on what ran before)."""
        from mehs.ssr.tiling_onnx_probes import onnx_file_key

        return cls(None, key=lambda: onnx_file_key(model))

    def _resolve(self) -> tuple[Path | None, str | None]:
        if self._where is None:
            folder = cache_dir()
            if folder is None:
                key = None
            elif self._key is not None:
                key = self._key()
            else:
                key = network_key(self._network)
            self._where = (None if key is None else folder / "tiling" / f"{key[:32]}.json", key)
        return self._where

    @property
    def path(self) -> Path | None:
        """The cache file, or None when the network is not cached."""
        return self._resolve()[0]

    @property
    def key(self) -> str | None:
        return self._resolve()[1]

    def _load(self) -> dict:
        if self._data is None:
            self._data = {}
            if self.path is not None:
                try:
                    doc = json.loads(self.path.read_text())
                    if (isinstance(doc, dict) and doc.get("format") == FORMAT
                            and doc.get("key") == self.key):
                        self._data = {k: v for k, v in doc.get("probes", {}).items()
                                      if k in _KINDS and isinstance(v, _KINDS[k])
                                      and not isinstance(v, bool)}
                except (OSError, ValueError):
                    pass                    # missing or damaged: measured again, rewritten
        return self._data

    def measured(self, kind: str, measure):
        """``measure`` behind the store: a callable giving the stored figure if there is
        one, else measuring it and storing it."""
        def get():
            v = self.get(kind)
            if v is None:
                v = measure()
                self.put(kind, v)
            return v
        return get

    def get(self, kind: str):
        """The stored figure, or None."""
        return self._load().get(kind)

    def put(self, kind: str, value) -> None:
        """Store a measured figure (nothing when the network is not cacheable)."""
        if self.path is None or kind not in _KINDS:
            return
        if kind == "memory":
            value = {k: (float(v) if isinstance(v, (int, float)) else v) for k, v in value.items()}
        data = self._load()
        data[kind] = value
        from mehs.errors import MehsError
        from mehs.io.atomic import write_json_atomic

        try:
            write_json_atomic(self.path, {"format": FORMAT, "key": self.key, "probes": data})
        except (OSError, MehsError):    # a read-only or full cache: measured again next time
            pass
