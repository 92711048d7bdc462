"""How the C heap holds a network's tensors: memory per counted byte, and heap reuse.

:func:`mehs.ssr.tiling_probes.torch_memory_probe` counts the bytes of live tensors;
what the process holds is more, by an amount that depends on glibc's allocator.
By default glibc maps every block above its mmap threshold (which grows to
32 MiB) afresh and returns it on free, and serves smaller ones from its heap:
:func:`allocator_overhead` models that. :func:`reused_heap` instead serves a
tiled inference's tensors from the heap and keeps freed blocks for the next layer
and the next tile: no page is faulted in twice, at the cost of the heap's holes
(:data:`HEAP_REUSE_OVERHEAD`).
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import numpy as np

from mehs import _heap

#: Resident memory per byte the memory probe counts, for a call on this many
#: pixels or more (see :func:`allocator_overhead`).
ALLOCATOR_OVERHEAD = 1.15
#: Calls on fewer pixels than this keep more of their memory on the C heap.
HEAP_PIXELS = 1_200_000
#: Resident bytes per counted byte of a call run inside :func:`reused_heap`.
HEAP_REUSE_OVERHEAD = 1.7

#: What the dynamic thresholds settle at in a process that has freed a large block
#: (glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64-bit, and twice that for trimming):
#: where :func:`reused_heap` leaves them.
_SETTLED_MMAP, _SETTLED_TRIM = 32 << 20, 64 << 20
_REUSE = 1 << 30


def trim_heap() -> None:
    """Return the C heap's free memory to the system (glibc ``malloc_trim``; elsewhere nothing).

    glibc keeps freed blocks below its mmap threshold resident; after a network
    run that is up to a few hundred MB the next tile could reuse, but that the
    resident-memory figure counts as held.
    """
    _heap.trim()


def allocator_overhead(pixels: float) -> float:
    """Resident bytes per byte counted by :func:`torch_memory_probe`, for a call on ``pixels``.

    The probe counts live tensors and convolution reorders. glibc serves
    blocks under its mmap threshold (which grows to 32 MiB) from its heap, whose
    freed blocks are reused imperfectly, so the smaller the call, the larger the
    share of its tensors there and the more resident memory per counted byte.
    Measured on the small hdrssr net (resident growth of one call after
    ``malloc_trim``): ×1.12 at 1.1 M pixels, ×1.2 at 0.79 M, ×1.31 at 0.52 M,
    ×1.40–1.68 at 0.29 M. Modelled as ``1.15 + 0.2 log2(HEAP_PIXELS / pixels)``
    within [1.15, 1.8].
    """
    if pixels <= 0:
        return 1.8
    return float(np.clip(ALLOCATOR_OVERHEAD + 0.2 * np.log2(HEAP_PIXELS / pixels),
                         ALLOCATOR_OVERHEAD, 1.8))


def heap_reuse_overhead(pixels: float) -> float:
    """Resident bytes per counted byte for a call inside :func:`reused_heap`.

    Measured on the small hdrssr net (peak resident growth of one call after
    ``malloc_trim``, thresholds at 1 GiB): ×1.16 at 0.59 M pixels, ×1.17 at 0.79 M,
    ×1.48 at 0.72 M, ×1.19–1.53 at 1.1 M — the heap's holes depend on the order of
    frees more than on the size — and ×1.83 for two 0.29 M-pixel tiles in a row.
    Taken as :data:`HEAP_REUSE_OVERHEAD`, or 0.35 above the default allocator's
    figure where that is higher (small calls), at most 2.2.
    """
    return min(max(HEAP_REUSE_OVERHEAD, allocator_overhead(pixels) + 0.35), 2.2)


def heap_reuse_available() -> bool:
    """Whether :func:`reused_heap` can act here (glibc)."""
    return _heap.available()


@contextlib.contextmanager
def reused_heap(enable: bool = True) -> Iterator[bool]:
    """Within the block, serve blocks up to 1 GiB from the C heap and keep freed ones.

    With glibc's defaults every tensor above the mmap threshold is a fresh mapping,
    faulted in page by page and unmapped on free; a network call re-faulted its
    whole working set layer after layer — on this project's VM 40–75 % of an
    inference's CPU time was in the kernel (issue 16). Kept on the heap, freed
    blocks serve the next layer and the next tile: the small hdrssr net on a
    1088×1024 tile ran 3.0–3.7 s instead of 5.7–6.8 s, system time 1.2–1.3 s
    instead of 4.5–5.5 s, at ×1.2–1.5 resident memory per counted byte instead of
    ×1.0 (:func:`heap_reuse_overhead`). On leaving, the thresholds are set where a
    long-running process's dynamic ones settle (32 MiB mmap, 64 MiB trim) and the
    heap's free memory is returned (``malloc_trim``). Yields whether it acted
    (False with ``enable=False`` or without glibc).
    """
    if not (enable and _heap.set_thresholds(_REUSE, _REUSE)):
        yield False
        return
    try:
        yield True
    finally:
        _heap.set_thresholds(_SETTLED_MMAP, _SETTLED_TRIM)
        _heap.trim()
