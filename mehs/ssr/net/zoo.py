"""The SSR network zoo: one dispatcher dict of architectures, their presets, published
parameter counts, and the builder every trainer and loader uses.

``ARCHITECTURES[name]`` is an :class:`Architecture`; calling it builds a network:
``ARCHITECTURES["mstpp"]("full")``. :func:`build_network` builds from a
:class:`~mehs.ssr.net.base.NetConfig` (what checkpoints store).
:func:`parameter_table` / :func:`print_parameter_table` compare the full presets with
the published counts (``python -m mehs.ssr.net``).

References
----------
See each architecture's module: :mod:`~mehs.ssr.net.hdrssr`,
:mod:`~mehs.ssr.net.mikamoto`, :mod:`~mehs.ssr.net.galliani2017`,
:mod:`~mehs.ssr.net.hscnnd2018`, :mod:`~mehs.ssr.net.awan2020`,
:mod:`~mehs.ssr.net.mstpp2022`.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any

from mehs.errors import InputError
from mehs.ssr.net.awan2020 import AWAN2020
from mehs.ssr.net.base import NetConfig, SSRNetwork, count_parameters
from mehs.ssr.net.galliani2017 import Galliani2017
from mehs.ssr.net.hdrssr import HDRSSR
from mehs.ssr.net.hscnnd2018 import HSCNND2018
from mehs.ssr.net.mikamoto import MikamotoTwoBranch
from mehs.ssr.net.mstpp2022 import MSTPlusPlus2022

#: Presets every architecture has.
PRESETS = ("full", "small", "tiny")


@dataclass(frozen=True)
class Architecture:
    """One zoo entry: the network class, a one-line title, the published parameter count
    of its full preset (``None`` when none is published) and where it is published,
    and the training-recipe changes the paper made for it."""

    name: str
    cls: type
    title: str
    published_params: float | None = None
    published_source: str = ""
    recipe: dict[str, float] = field(default_factory=dict)

    @property
    def presets(self) -> dict[str, dict[str, Any]]:
        return self.cls.PRESETS

    def params(self, preset: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        """The preset's architecture parameters with ``overrides`` applied, checked."""
        if preset not in self.presets:
            raise InputError(f"architecture {self.name!r} has no preset {preset!r}; "
                             f"choose one of {sorted(self.presets)}")
        p = {**self.presets[preset], **(overrides or {})}
        allowed = _accepted_params(self.cls, self.presets)
        unknown = sorted(set(p) - allowed)
        if unknown:
            raise InputError(f"architecture {self.name!r} has no parameter(s) {unknown}; "
                             f"it takes {sorted(allowed)}")
        _check_sizes(self.name, p)
        return p

    def __call__(self, preset: str = "small", **config) -> SSRNetwork:
        """Build the network: ``config`` holds :class:`NetConfig` fields (``mode``,
        ``wavelengths``, ``reinhard``, ``params``, …)."""
        return build_network(NetConfig(arch=self.name, preset=preset, **config))


def _accepted_params(cls, presets) -> set[str]:
    names = set().union(*(set(p) for p in presets.values()))
    sig = inspect.signature(cls.__init__)
    names |= {k for k, v in sig.parameters.items()
              if k not in ("self", "config") and v.kind is v.KEYWORD_ONLY}
    return names


def _check_sizes(arch: str, p: dict[str, Any]) -> None:
    # torch fails late ("negative dimension") or builds empty layers for these
    for k, v in p.items():
        if isinstance(v, bool) or k in ("dropout",):
            continue
        vals = list(v) if isinstance(v, (list, tuple)) else [v]
        for x in vals:
            if isinstance(x, bool) or not isinstance(x, int) or x < (0 if k == "levels" else 1):
                raise InputError(f"{arch}: parameter {k} must be a positive whole number, "
                                 f"got {v!r}")
        if isinstance(v, (list, tuple)) and not vals:
            raise InputError(f"{arch}: parameter {k} must not be empty")
    d = p.get("dropout", 0.0)
    if not (isinstance(d, (int, float)) and 0 <= d < 1):
        raise InputError(f"{arch}: dropout must be in [0, 1), got {d!r}")


#: The zoo, by name (the ``--arch`` of ``mehs train-ssr``).
ARCHITECTURES: dict[str, Architecture] = {a.name: a for a in (
    Architecture("hdrssr", HDRSSR,
                 "the HDR SSR paper's network: two-branch FC-DenseNet with channel attention"),
    Architecture("mikamoto", MikamotoTwoBranch,
                 "Mikamoto et al. two-branch network (sigmoid + Mexican hat), no attention"),
    Architecture("galliani", Galliani2017, "Galliani et al. 2017, FC-DenseNet (dropout)",
                 1.5e6, "Jégou et al. 2017, Table 1 (FC-DenseNet56, the 56-layer Tiramisu)"),
    Architecture("hscnnd", HSCNND2018, "HSCNN-D, Shi et al. 2018",
                 4.65e6, "Cai et al. 2022 (MST++), Table 1: HSCNN+ 4.65 M"),
    Architecture("awan", AWAN2020, "AWAN, Li et al. 2020",
                 4.04e6, "Cai et al. 2022 (MST++), Table 1: AWAN 4.04 M",
                 recipe=dict(AWAN2020.RECIPE)),
    Architecture("mstpp", MSTPlusPlus2022, "MST++, Cai et al. 2022",
                 1.62e6, "Cai et al. 2022 (MST++), Table 1: MST++ 1.62 M"),
)}


def get_architecture(name: str) -> Architecture:
    try:
        return ARCHITECTURES[name]
    except KeyError:
        raise InputError(f"unknown network architecture {name!r}; choose one of "
                         f"{sorted(ARCHITECTURES)}") from None


def build_network(config: NetConfig | dict | None = None, **overrides) -> SSRNetwork:
    """Build a network from a :class:`NetConfig` (or its dict form) with overrides.

    ``overrides`` may name :class:`NetConfig` fields (``arch``, ``preset``, ``mode``, …)
    or architecture parameters (``growth=4`` → ``params``). The keywords of checkpoint
    format 1 still work: ``build_network(variant="hdrssr", first_channels=8, …)``.
    """
    if config is None:
        d: dict[str, Any] = {}
    elif isinstance(config, NetConfig):
        d = config.to_dict()
        d.pop("variant")
    else:
        d = dict(config)
    fields = set(NetConfig.__dataclass_fields__) | {"variant"}
    params = dict(d.get("params") or {})
    for k, v in overrides.items():
        if k in fields:
            d[k] = v
        else:
            params[k] = v
    if "variant" in d and "arch" in d:
        d.pop("variant")  # an explicit arch wins over a stale label
    d["params"] = params
    cfg = NetConfig.from_dict(d)
    arch = get_architecture(cfg.arch)
    p = arch.params(cfg.preset, cfg.params)
    return arch.cls(cfg, **p)


def parameter_table(archs=None) -> list[dict[str, Any]]:
    """Parameter counts of every architecture's presets (31 bands) beside the published
    figure: rows ``{arch, title, full, small, published, source, ratio}``."""
    rows = []
    for name in archs or ARCHITECTURES:
        a = get_architecture(name)
        full = count_parameters(a("full"))
        small = count_parameters(a("small"))
        ratio = full / a.published_params if a.published_params else None
        rows.append(dict(arch=name, title=a.title, full=full, small=small,
                         published=a.published_params, source=a.published_source,
                         ratio=ratio))
    return rows


def format_parameter_table(rows=None) -> str:
    """:func:`parameter_table` as a Markdown table."""
    rows = parameter_table() if rows is None else rows
    out = ["| arch | network | full preset | published | full / published | small preset | source |",
           "|---|---|---:|---:|---:|---:|---|"]
    for r in rows:
        pub = f"{r['published'] / 1e6:.2f} M" if r["published"] else "–"
        ratio = f"{r['ratio']:.3f}" if r["ratio"] else "–"
        out.append(f"| {r['arch']} | {r['title']} | {r['full'] / 1e6:.3f} M | {pub} | {ratio} "
                   f"| {r['small'] / 1e3:.1f} k | {r['source'] or '–'} |")
    return "\n".join(out)


def print_parameter_table() -> None:
    """Print :func:`format_parameter_table` (``python -m mehs.ssr.net``)."""
    print(format_parameter_table())
