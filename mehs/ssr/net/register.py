"""Registers the networks with the SSR registry (:mod:`mehs.ssr.registry`).

Imported by :func:`mehs.ssr.registry.load_providers`. It

1. imports every module of :mod:`mehs.ssr.net` (so an architecture module that
   calls :func:`~mehs.ssr.registry.register_architecture` at import time is
   found without editing this file; one that fails to import is skipped and
   listed in :data:`SKIPPED`);
2. adopts the zoo's own dispatcher dict (``mehs.ssr.net.zoo.ARCHITECTURES``),
   and ``fcdensenet`` for format-1 checkpoints of that name (the zoo migrates
   their configuration);
3. makes every registered architecture a model name:
   ``load_model("hdrssr", checkpoint="runs/x/best.pt")`` (the checkpoint must
   hold that architecture); naming a ``.pt`` file directly works too.
"""

from __future__ import annotations

import importlib
import pkgutil

from mehs.errors import InputError
from mehs.ssr.registry import ARCHITECTURES, Architecture, register_architecture, register_model

#: ``module name → error`` of net modules that did not import.
SKIPPED: dict[str, str] = {}
_NOT_ARCH = {"register", "export", "train", "layers", "basis", "zoo", "__main__"}


def _import_net_modules() -> None:
    import mehs.ssr.net as pkg

    for info in pkgutil.iter_modules(pkg.__path__):
        if info.name.startswith("_") or info.name in _NOT_ARCH:
            continue
        try:
            importlib.import_module(f"{pkg.__name__}.{info.name}")
        except Exception as exc:  # one broken architecture must not hide the others
            SKIPPED[info.name] = f"{type(exc).__name__}: {exc}"


def _checkpoint_factory(arch: str):
    def make(checkpoint=None, path=None, name=None, device: str = "cpu"):
        from mehs.ssr.net.export import load_torch_model

        ckpt = checkpoint or path
        if ckpt is None:
            raise InputError(f"model {arch!r} needs a trained checkpoint: "
                             f"load_model({arch!r}, checkpoint='OUT/best.pt') "
                             f"(train one with `mehs train-ssr DATASET`)")
        model = load_torch_model(ckpt, name=name, device=device)
        if model.arch != arch:
            raise InputError(f"holds a {model.arch!r} network, not {arch!r}", ckpt)
        return model

    make.__name__ = f"make_{arch}"
    return make


def _register_zoo() -> bool:
    """Adopt a zoo module's own dispatcher dict (``mehs.ssr.net.zoo.ARCHITECTURES``, entries
    with ``cls``, ``presets``, ``title``, ``published_params``) if there is one; True if so.

    Such networks take the zoo's ``NetConfig`` dict (``arch``, ``preset``, ``mode``, …) and
    learn in both modes; they are trained through ``mehs train-ssr --arch`` (no hook).
    """
    try:
        zoo = importlib.import_module("mehs.ssr.net.zoo")
    except Exception as exc:
        if not isinstance(exc, ModuleNotFoundError) or exc.name != "mehs.ssr.net.zoo":
            SKIPPED["zoo"] = f"{type(exc).__name__}: {exc}"
        return False
    entries = getattr(zoo, "ARCHITECTURES", None)
    if not isinstance(entries, dict) or not callable(getattr(zoo, "build_network", None)):
        return False

    def build(net_config: dict):
        return zoo.build_network(dict(net_config))

    for name, a in entries.items():
        if name in ARCHITECTURES:
            continue
        pub = getattr(a, "published_params", None)
        register_architecture(Architecture(
            name, build, presets=dict(getattr(a, "presets", {}) or {}),
            learning=("similarity", "e2e"), description=str(getattr(a, "title", name)),
            reference=str(getattr(a, "published_source", "")),
            published_params=None if pub is None else int(round(pub))))
    # format-1 checkpoints named "fcdensenet": the zoo's build migrates their configuration
    if "fcdensenet" not in ARCHITECTURES:
        register_architecture(Architecture("fcdensenet", build, learning=("e2e",),
                                           description="older FC-DenseNet checkpoints (migrated)",
                                           listed=False))
    return True


_import_net_modules()
_register_zoo()
for _arch in list(ARCHITECTURES.values()):
    register_model(_arch.name, _checkpoint_factory(_arch.name),
                   description=f"{_arch.description} (torch; needs checkpoint=)", overwrite=True)
