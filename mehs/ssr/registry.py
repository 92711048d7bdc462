"""The SSR model registry: names → model factories, architecture names → builders.

Bottom of the package (imports only :mod:`mehs.ssr.contract`), so baselines
(:mod:`mehs.ssr.baselines`) and networks (:mod:`mehs.ssr.net`) register *into*
it without importing the loader (:mod:`mehs.ssr.models`), which imports them.
Imports flow one way::

    preprocess ← contract ← registry ← baselines, net.* ← models (load_model) ← evaluation

Two tables, one dispatcher dict each:

:data:`MODELS`
    ``name → ModelEntry(factory)``; ``load_model("smits")`` calls
    ``factory(**kwargs)``. :func:`register_model` adds one.
:data:`ARCHITECTURES`
    ``arch → Architecture``: how to build a torch network from the
    configuration stored in a checkpoint, its presets, its learning modes and
    its reference. :func:`register_architecture` adds one; the checkpoint
    loader (:func:`mehs.ssr.net.export.load_torch_model`) dispatches on the
    checkpoint's ``arch`` through :func:`get_architecture`. See docs/ssr.md,
    "Adding an architecture", for the whole contract.

Modules that register are listed in :data:`PROVIDERS` and imported on first
use by :func:`load_providers` (the torch ones quietly skipped without torch).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Callable

from mehs.errors import InputError

#: Modules that register models or architectures when imported. The first must
#: import; the others are optional (torch extra) and skipped when they fail.
PROVIDERS: list[str] = ["mehs.ssr.baselines", "mehs.ssr.net.register"]


@dataclass
class ModelEntry:
    """A registry entry: ``factory(**kwargs)`` returns a model."""

    name: str
    factory: Callable[..., Any]
    description: str = ""


@dataclass
class Architecture:
    """A network architecture the checkpoint loader can rebuild.

    Attributes
    ----------
    name
        The ``arch`` recorded in checkpoints (``--arch`` of ``mehs train-ssr``).
    build
        ``build(net_config: dict) -> torch.nn.Module``; the module's
        ``forward(rgb (N, 3, H, W) linear) -> (N, B, H, W)`` applies the
        checkpoint's declared pre-processing itself and returns a shape S
        (``output="shape"``) or spectra (``"spectra"``); it has a
        ``wavelengths`` attribute (``(B,)`` nm).
    presets
        Preset name → ``net_config`` overrides (e.g. ``"full"``, ``"small"``).
    learning
        Learning modes it supports: subset of ``("similarity", "e2e")``.
    description, reference
        One line each, for listings and reports.
    published_params
        Parameter count of the full preset as published (``None`` if not).
    train
        Optional ``train(dataset, out_dir, *, preset, learning, preprocessing,
        input, epochs, device, seed, progress, options) -> Path`` (the best
        checkpoint), resuming when ``out_dir/last.pt`` exists; used by
        ``mehs paper``. Without it ``mehs paper`` runs
        ``mehs train-ssr DATASET --arch NAME …``.
    listed
        False for aliases kept only so older checkpoints load (not trained by
        ``mehs paper``, not in :func:`list_architectures`).
    """

    name: str
    build: Callable[[dict], Any]
    presets: dict[str, dict] = field(default_factory=dict)
    learning: tuple[str, ...] = ("similarity", "e2e")
    description: str = ""
    reference: str = ""
    published_params: int | None = None
    train: Callable[..., Any] | None = None
    listed: bool = True


#: Registered models by name (see :func:`register_model`).
MODELS: dict[str, ModelEntry] = {}
#: Registered network architectures by ``arch`` name (see :func:`register_architecture`).
ARCHITECTURES: dict[str, Architecture] = {}
_LOADED = False


def _key(name: str) -> str:
    key = str(name).strip().lower()
    if not key or any(c in key for c in ",:/\\= "):
        raise InputError(f"invalid model name {name!r} (no spaces or , : / \\ =)")
    return key


def register_model(name: str, factory: Callable[..., Any], *, description: str = "",
                   overwrite: bool = False) -> None:
    """Register ``factory`` (called with ``**kwargs``, returns a model) under ``name``."""
    key = _key(name)
    if key in MODELS and not overwrite:
        raise InputError(f"a model named {key!r} is already registered")
    MODELS[key] = ModelEntry(key, factory, description)


def register_architecture(arch: Architecture, *, overwrite: bool = False) -> Architecture:
    """Register a network architecture (see :class:`Architecture`); returns it."""
    key = _key(arch.name)
    if key in ARCHITECTURES and not overwrite:
        raise InputError(f"an architecture named {key!r} is already registered")
    bad = set(arch.learning) - {"similarity", "e2e"}
    if bad or not arch.learning:
        raise InputError(f"architecture {key!r}: learning modes must be among "
                         f"'similarity', 'e2e', got {arch.learning}")
    arch.name = key
    ARCHITECTURES[key] = arch
    return arch


def load_providers() -> None:
    """Import the registering modules once (see :data:`PROVIDERS`)."""
    global _LOADED
    if _LOADED:
        return
    importlib.import_module(PROVIDERS[0])
    _LOADED = True
    for mod in PROVIDERS[1:]:
        try:
            importlib.import_module(mod)
        except (ImportError, OSError):
            pass  # torch (or a network module) absent or broken: its entries stay unlisted


def get_architecture(arch: str) -> Architecture:
    """The registered :class:`Architecture` named ``arch`` or a clear :class:`InputError`."""
    load_providers()
    entry = ARCHITECTURES.get(str(arch).strip().lower())
    if entry is None:
        known = ", ".join(sorted(ARCHITECTURES)) or "none (is the torch extra installed?)"
        raise InputError(f"unknown network architecture {arch!r}; registered: {known}")
    return entry


def list_architectures() -> dict[str, Architecture]:
    """Listed architectures by name (after loading the providers)."""
    load_providers()
    return {k: v for k, v in sorted(ARCHITECTURES.items()) if v.listed}
