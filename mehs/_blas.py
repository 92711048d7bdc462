"""One-thread BLAS for the hot paths' many small matrix products.

Resampling a memory-mapped cube (one ``(31, 204) @ (204, samples)`` product per
line) and the Smits / Mallett baselines (a ``(pixels, 7) @ (7, 31)`` product per
block) issue hundreds of small, memory-bound GEMMs. OpenBLAS splits each over
all cores and its threads spin-wait for one another at the end of every call;
when another process holds one of the cores, every call waits for a time
slice, and the stage slowed down 6–100× on a 2-core machine with one competing
job (issue 16). One thread per call costs little on a quiet machine (the
products are bound by memory bandwidth, not by arithmetic) and does not
degrade under load. :func:`single_thread_blas` pins numpy's BLAS to one thread
for the duration of a ``with`` block through threadpoolctl, and restores the
previous setting afterwards.

The controller is built once (scanning the loaded libraries takes ~1 ms) and
only for the BLAS that numpy links; a change of thread count is one call into
OpenBLAS (~10 µs). The setting is process-wide: concurrent threads of one
process that use BLAS see it too (mehs parallelises across processes).

References
----------
- threadpoolctl, https://github.com/joblib/threadpoolctl (``ThreadpoolController.limit``).
"""

from __future__ import annotations

import contextlib
from functools import lru_cache
from typing import Iterator


@lru_cache(maxsize=1)
def _numpy_blas():
    """threadpoolctl handle of the BLAS numpy links, or None (none found / not installed)."""
    import numpy  # noqa: F401  (the library must be loaded before it can be found)

    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # an install without threadpoolctl still computes the same numbers
        return None
    blas = ThreadpoolController().select(user_api="blas")
    return blas if len(blas.lib_controllers) else None


@contextlib.contextmanager
def single_thread_blas() -> Iterator[None]:
    """Run the block with numpy's BLAS limited to one thread (a no-op without threadpoolctl)."""
    blas = _numpy_blas()
    if blas is None:
        yield
        return
    with blas.limit(limits=1):
        yield
