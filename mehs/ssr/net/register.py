"""Registers the networks with the SSR registry (:mod:`mehs.ssr.registry`).

Imported by :func:`mehs.ssr.registry.load_providers`. It

1. imports every module of :mod:`mehs.ssr.net` (so an architecture module that
   calls :func:`~mehs.ssr.registry.register_architecture` at import time is
   found without editing this file; one that fails to import is skipped and
   listed in :data:`SKIPPED`);
2. adopts the zoo's own dispatcher dict (``mehs.ssr.net.zoo.ARCHITECTURES``)
   when there is one; without a zoo, registers the two variants of
   :mod:`mehs.ssr.net.model` as architectures ``hdrssr`` (learns spectral
   similarity) and ``fcdensenet`` (end to end), unless a module registered
   those names already;
3. makes every registered architecture a model name:
   ``load_model("hdrssr", checkpoint="runs/x/best.pt")`` (the checkpoint must
   hold that architecture); naming a ``.pt`` file directly works too.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

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


def _legacy_build(variant: str):
    def build(net_config: dict):
        from mehs.ssr.net.model import NetConfig, build_network

        return build_network(NetConfig.from_dict({**net_config, "variant": variant}))

    return build


def _legacy_train(variant: str):
    def train(dataset, out_dir, *, preset: str = "small", learning: str | None = None,
              preprocessing=None, input: str = "hdr", epochs: int = 40, device: str = "cpu",
              seed: int = 0, progress: bool = True, options: dict | None = None) -> Path:
        """Train one ``variant`` network on ``dataset``; returns the best checkpoint."""
        from mehs.cli.train_ssr import NET_SIZES, _splits, load_training_pairs
        from mehs.ssr.net.model import NetConfig
        from mehs.ssr.net.train import TrainConfig, train_network

        if preprocessing is not None and (preprocessing.key is not None or preprocessing.scale != 1):
            raise InputError(f"{variant}: the network applies the paper's x/(1+x) at scale 1 "
                             f"only, not {preprocessing.label()}")
        opts = dict(options or {})
        tr, va = _splits(dataset)
        pairs, wl = load_training_pairs(dataset, split=tr, kind=input)
        val = load_training_pairs(dataset, split=va, kind=input)[0] if va else []
        nc = NetConfig(variant=variant, wavelengths=wl.tolist(), reinhard=preprocessing is not None,
                       **NET_SIZES[preset])
        tc = TrainConfig(epochs=epochs, seed=seed, device=device,
                         **{k: v for k, v in opts.items() if k in TrainConfig.__dataclass_fields__})
        res = train_network(pairs, out_dir, net_config=nc, train_config=tc, val_pairs=val,
                            resume=(Path(out_dir) / "last.pt").is_file(), progress=progress,
                            extra={"dataset": str(Path(dataset).resolve()), "input": input,
                                   "train_split": tr, "val_split": va, "preset": preset})
        return Path(res.best_checkpoint or res.last_checkpoint)

    return train


def _legacy_presets() -> dict[str, dict]:
    from mehs.cli.train_ssr import NET_SIZES

    return {k: dict(v) for k, v in NET_SIZES.items()}


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
if not _register_zoo() and "hdrssr" not in ARCHITECTURES:
    register_architecture(Architecture(
        "hdrssr", _legacy_build("hdrssr"), presets=_legacy_presets(), learning=("similarity",),
        description="FC-DenseNet + channel attention + sigmoid/Mexican-hat basis branches, "
                    "learns spectral similarity (mehs.ssr.net.model)",
        reference="HDR SSR by learning only spectral similarity (the paper's network)",
        train=_legacy_train("hdrssr")))
if "fcdensenet" not in ARCHITECTURES:  # the single-architecture release, before a zoo
    register_architecture(Architecture(
        "fcdensenet", _legacy_build("fcdensenet"), presets=_legacy_presets(), learning=("e2e",),
        description="the same FC-DenseNet with a 1×1 conv to 31 bands, MSE on spectra, end to end",
        reference="Galliani et al. 2017 style (with channel attention)",
        train=_legacy_train("fcdensenet")))
for _arch in list(ARCHITECTURES.values()):
    register_model(_arch.name, _checkpoint_factory(_arch.name),
                   description=f"{_arch.description} (torch; needs checkpoint=)", overwrite=True)
