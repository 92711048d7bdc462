"""One BLAS thread while any scene is being built in this process.

A multi-threaded BLAS may split a product differently for different thread
counts, and the thread count followed ``--workers``: the last bits of the
dataset changed with it. Scenes are therefore built with one BLAS thread.
The limit is process-wide (threadpoolctl sets it in the BLAS library), so
concurrent scene builds in one process (Dask's threaded workers) share one
reference-counted limit: the first to enter sets it, the last to leave
restores the previous setting — never one build restoring it under another.

References
----------
threadpoolctl — https://github.com/joblib/threadpoolctl
"""

from __future__ import annotations

import contextlib
import threading

_LOCK = threading.Lock()
_USERS = 0
_LIMITER = None


@contextlib.contextmanager
def one_blas_thread():
    """Context in which BLAS (OpenBLAS, MKL, BLIS) uses a single thread."""
    global _USERS, _LIMITER
    from threadpoolctl import threadpool_limits

    with _LOCK:
        if _USERS == 0:
            _LIMITER = threadpool_limits(limits=1, user_api="blas")
        _USERS += 1
    try:
        yield
    finally:
        with _LOCK:
            _USERS -= 1
            if _USERS == 0 and _LIMITER is not None:
                _LIMITER.restore_original_limits()
                _LIMITER = None
