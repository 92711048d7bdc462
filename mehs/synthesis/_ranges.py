"""Index ranges run on a thread pool of numba's thread count (issue 16).

The synthesis kernels are serial and release the GIL: numba's ``parallel=True``
compiled for most of a first-ever run. :func:`run_ranges` is how both the merge
(chunks of lines) and the response solver (channel ranges) use several cores.
"""

from __future__ import annotations

import os
import sys
from typing import Callable


def thread_count() -> int:
    """numba's thread count, without importing numba when nothing else has.

    ``numba.get_num_threads()`` once numba is loaded (``numba.set_num_threads`` may
    have lowered it); before that, what numba would start with: ``NUMBA_NUM_THREADS``,
    else the CPUs this process may run on. A merge whose machine code is loaded
    directly (:mod:`mehs.synthesis._native`) never starts numba for this.
    """
    if "numba" in sys.modules:
        from numba import get_num_threads

        return int(get_num_threads())
    env = os.environ.get("NUMBA_NUM_THREADS", "").strip()
    if env.isdigit() and int(env) > 0:
        return int(env)
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:      # not Linux
        return os.cpu_count() or 1


def run_ranges(n: int, run: Callable[[int, int], None], *, max_step: int | None = None,
               name: str = "mehs") -> None:
    """Call ``run(i0, i1)`` over ``[0, n)`` split into ranges of at most ``max_step``.

    With one thread (``NUMBA_NUM_THREADS`` / ``numba.set_num_threads``, e.g. one per
    build worker) the ranges run in order here; otherwise on that many threads, at
    least two ranges per thread so that one slow range does not idle the rest. The
    first exception of a range is raised once all have ended.
    """
    max_step = n if max_step is None else max(1, int(max_step))
    nthreads = max(1, min(thread_count(), n))
    step = max_step if nthreads == 1 else max(1, min(max_step, -(-n // (2 * nthreads))))
    starts = range(0, n, step)
    if nthreads == 1 or len(starts) == 1:
        for i0 in starts:
            run(i0, min(n, i0 + step))
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(nthreads, thread_name_prefix=name) as pool:
        for f in [pool.submit(run, i0, min(n, i0 + step)) for i0 in starts]:
            f.result()
