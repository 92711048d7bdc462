"""The kernels :mod:`mehs.synthesis._native` stores, described for it (issue 16).

Each :class:`Spec` names the compiled kernel, lists its parameters (from which the C
entry point and its ctypes wrapper are made) and the source files its machine code
depends on, and brings a shape check that runs before every call: the kernels index
without bounds checks, so an array of the wrong extent must never reach them.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

#: A kernel's parameters, in order: ``(name, type)``. Types: ``"zs:N"`` a tuple of
#: ``P`` raw-dtype arrays of ``N`` dimensions (one per exposure); ``"raw:N"`` one
#: raw-dtype array; ``"f4s:N"`` a tuple of ``P`` float32 arrays (per-exposure scratch);
#: ``"<numpy type>:N"`` (``f4``, ``f8``, ``i4``, ``i8``, ``u1``, ``u2``) an array
#: of ``N`` dimensions; ``"f4"``, ``"f8"``, ``"i8"``, ``"b1"`` scalars. An array reaches the
#: C entry point as its data pointer followed by its shape.
_MERGE_HEAD = (("zs", "zs:3"), ("darks", "f4:3"), ("sat", "f4:1"), ("times", "f4:1"))
_MERGE_TAIL = (("gain", "f8"), ("avar", "f4:1"), ("rel_var", "f8"), ("cal", "f4:1"),
               ("want_chi2", "b1"), ("clip", "b1"), ("output 0", "f4:3"), ("output 1", "f4:2"),
               ("output 2", "i4:2"), ("output 3", "f4:2"), ("output 4", "i4:2"),
               ("output 5", "i4:2"), ("output 6", "f4:2"))
_WEIGHTED = _MERGE_HEAD + (("L", "i8"), ("floor", "f4")) + _MERGE_TAIL
_MERGE_SOURCES = ("_merge_fused.py", "_merge_fused_weighted.py", "_merge_binned.py",
                  "_merge_binned_weighted.py", "_merge_rows.py", "_cephes.py")
_PTC_COMMON = (("y_j", "raw:2"), ("y_k", "raw:2"), ("raw_j", "f4:2"), ("raw_k", "f4:2"),
               ("sat", "f4:1"), ("nbr", "i8:1"), ("cell_bits", "i8"), ("key_row", "i4:1"),
               ("cp", "i4:1"), ("sat_row", "u1:1"), ("bp", "u1:1"))
_PTC_SOURCES = ("_ptc_kernels.py", "_cephes.py")


def _check_merge(P, args) -> None:
    """The shapes the merge kernels assume (they index without bounds checks)."""
    zs, darks, sat, times = args[:4]
    out, *aux = args[-7:]
    avar, cal = args[-12], args[-10]
    _check_merge_arrays(P, zs, darks, sat, times, avar, cal, out, aux)


def _check_merge_binned(P, args) -> None:
    """:func:`_check_merge`'s shapes, and the binned kernel's bin width and scratch."""
    zs, darks, sat, times = args[:4]
    out, *aux = args[-7:]
    # the weighted kernels take L and floor after the times
    k = 2 if len(args) == len(_WEIGHTED_BINNED) else 0
    avar, cal, nbin, ysum, xps, bms = args[5 + k], args[7 + k], *args[10 + k:14 + k]
    _check_merge_arrays(P, zs, darks, sat, times, avar, cal, out, aux)
    ns = out.shape[2]
    if int(nbin) < 1:
        raise TypeError("native merge kernel: nbin must be at least 1")
    if any(a.shape != (ns,) for a in (*ysum, xps, bms)):
        raise TypeError(f"native merge kernel: the scratch rows must hold {ns} samples")


def _check_merge_arrays(P, zs, darks, sat, times, avar, cal, out, aux) -> None:
    nl, nb, ns = out.shape
    for j, z in enumerate(zs):
        if z.shape != (nl, nb, ns):
            raise TypeError(f"native merge kernel: exposure {j} has shape {z.shape}, "
                            f"the output {(nl, nb, ns)}")
    for what, a, shape in (("darks", darks, (P, nb, ns)), ("sat", sat, (nb,)),
                           ("times", times, (P,)), ("avar", avar, (P,)), ("cal", cal, (nb,))):
        if a.shape != shape:
            raise TypeError(f"native merge kernel: {what} must have shape {shape}")
    for k, a in enumerate(aux, start=1):
        if a.shape != (nl, ns):
            raise TypeError(f"native merge kernel: output {k} must have shape {(nl, ns)}")


def _check_ptc_samples(what, y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits) -> tuple[int, int]:
    """``(n, bands)``: the checks the photon-transfer kernels share (their samples, the
    bands' saturation and instruments, the cell bits)."""
    n, nb = y_j.shape
    for name, a in (("y_k", y_k), ("raw_j", raw_j), ("raw_k", raw_k)):
        if a.shape != (n, nb):
            raise TypeError(what + f"{name} must have shape {(n, nb)}")
    if sat.shape != (nb,) or nbr.shape != (nb,) or (nb and not (0 <= nbr.min() and nbr.max() < nb)):
        raise TypeError(what + "sat and nbr must have one entry per band, nbr naming bands")
    if not 1 <= int(cell_bits) <= 24:
        raise TypeError(what + "cell_bits must lie in 1..24")
    return n, nb


def _check_ptc_pass(P, args) -> None:
    """The shapes :func:`mehs.synthesis._ptc_kernels.ptc_pass` assumes."""
    (y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, *rows) = args[:11]
    (r, lo, table, med, lim, *sums) = args[11:]
    what = "native photon-transfer kernel: "
    n, nb = _check_ptc_samples(what, y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits)
    if any(a.shape != (nb,) for a in rows):
        raise TypeError(what + "scratch rows must have one entry per band")
    groups = med.shape[0]
    if lim.shape != (groups,) or any(a.shape != (groups,) for a in sums):
        raise TypeError(what + "one value per group expected")
    if table.size == 0 or int(lo) < 0 or int(lo) + table.shape[0] > 1 << int(cell_bits):
        raise TypeError(what + "the cell table lies outside the cells")
    if int(table.max()) >= groups:
        raise TypeError(what + "the cell table names unknown groups")


def _check_ptc_subset(P, args) -> None:
    """The shapes :func:`mehs.synthesis._ptc_kernels.ptc_subset` assumes."""
    (y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, step, r, *outs) = args
    what = "native photon-transfer subset kernel: "
    n, nb = _check_ptc_samples(what, y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits)
    if not 1 <= int(step) <= max(n * nb, 1):
        raise TypeError(what + f"step must lie in 1..{max(n * nb, 1)}")
    m = -(-(n * nb) // int(step))
    if any(a.shape[0] < m for a in outs[:4]) or outs[4].shape != (1,):
        raise TypeError(what + f"the outputs must hold {m} samples, the count one")


@dataclass(frozen=True)
class Spec:
    """A kernel with a stored entry point: where it lives, its parameters, the source
    files its machine code depends on (besides this module), a shape check and the
    arrays it writes (which must be writeable)."""

    module: str
    function: str
    params: tuple
    sources: tuple
    check: Callable
    per_exposure: bool = True      # takes one array per exposure (P ≥ 2)
    writes: tuple = ()             # the arrays it writes (outputs and scratch)

    def dispatcher(self) -> Callable:
        """The numba kernel itself (imports its module, and so numba)."""
        return getattr(importlib.import_module(self.module), self.function)


_POISSON = _MERGE_HEAD + _MERGE_TAIL
# the binned statistic's kernel: its bin width and scratch rows before the outputs
_BIN_SCRATCH = (("nbin", "i8"), ("ysum", "f4s:1"), ("xps", "f4:1"), ("bms", "i4:1"))
_POISSON_BINNED = _MERGE_HEAD + _MERGE_TAIL[:6] + _BIN_SCRATCH + _MERGE_TAIL[6:]
_WEIGHTED_BINNED = _WEIGHTED[:-7] + _BIN_SCRATCH + _WEIGHTED[-7:]
_MERGE_WRITES = tuple(f"output {i}" for i in range(7))
_PTC_SCRATCH = ("key_row", "cp", "sat_row", "bp")
KERNELS = {
    # each merge twice: with the χ² ghost statistic, and radiance-only ("_radiance")
    "poisson_linear": Spec("mehs.synthesis._merge_fused", "merge_chunk_poisson_linear",
                           _POISSON, _MERGE_SOURCES, _check_merge, writes=_MERGE_WRITES),
    "poisson_linear_radiance": Spec("mehs.synthesis._merge_fused",
                                    "merge_chunk_poisson_linear_radiance", _POISSON,
                                    _MERGE_SOURCES, _check_merge, writes=_MERGE_WRITES),
    "poisson_linear_binned": Spec("mehs.synthesis._merge_binned",
                                  "merge_chunk_poisson_linear_binned", _POISSON_BINNED,
                                  _MERGE_SOURCES, _check_merge_binned,
                                  writes=_MERGE_WRITES + ("ysum", "xps", "bms")),
    **{f"{m}_linear{v}": Spec("mehs.synthesis._merge_fused_weighted",
                              f"merge_chunk_{m}_linear{v}", _WEIGHTED, _MERGE_SOURCES,
                              _check_merge, writes=_MERGE_WRITES)
       for m in ("debevec", "robertson", "invvar") for v in ("", "_radiance")},
    **{f"{m}_linear_binned": Spec("mehs.synthesis._merge_binned_weighted",
                                  f"merge_chunk_{m}_linear_binned", _WEIGHTED_BINNED,
                                  _MERGE_SOURCES, _check_merge_binned,
                                  writes=_MERGE_WRITES + ("ysum", "xps", "bms"))
       for m in ("debevec", "robertson", "invvar")},
    "ptc_pass": Spec("mehs.synthesis._ptc_kernels", "ptc_pass",
                     _PTC_COMMON
                     + (("r", "f8"), ("lo", "i8"), ("table", "u2:1"), ("med", "f8:1"),
                        ("lim", "f8:1"), ("nall", "f8:1"), ("nbad", "f8:1"), ("nt", "f8:1"),
                        ("se", "f8:1"), ("se2", "f8:1"), ("syj", "f8:1")),
                     _PTC_SOURCES, _check_ptc_pass, per_exposure=False,
                     writes=_PTC_SCRATCH + ("nall", "nbad", "nt", "se", "se2", "syj")),
    "ptc_subset": Spec("mehs.synthesis._ptc_kernels", "ptc_subset",
                       _PTC_COMMON[:7]
                       + (("step", "i8"), ("r", "f8"), ("cells", "i4:1"), ("ds", "f8:1"),
                          ("qs", "f8:1"), ("pix", "i8:1"), ("count", "i8:1")),
                       _PTC_SOURCES, _check_ptc_subset, per_exposure=False,
                       writes=("cells", "ds", "qs", "pix", "count")),
}
