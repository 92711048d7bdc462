"""Numba's start-up without the parts mehs does not use (issue 16).

:func:`skip_scipy_linalg_import` runs before the first kernel of a fusion
(:func:`mehs.synthesis.fuse.fuse_bracket`).
"""

from __future__ import annotations

import sys


def skip_scipy_linalg_import() -> bool:
    """Let numba start without importing scipy.linalg (50-140 ms of every ``mehs fuse``).

    Loading even a cached kernel makes numba import ``numba.np.arraymath``, which
    asks ``ensure_blas()`` whether BLAS is there — by importing
    ``scipy.linalg.cython_blas``, hence all of scipy.linalg — only to enable
    ``np.dot`` and friends, which no mehs kernel uses. Here that module is imported
    with ``ensure_blas`` answering from ``find_spec`` (is scipy.linalg installed?);
    the real function is put back at once, so compiling a function that does use
    BLAS still imports and checks scipy's BLAS as numba would. Internals of numba:
    anything unexpected leaves numba to do as it always does. True if it applied.
    """
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return False
    try:
        import importlib.util

        import numba.np.linalg as nl

        real = nl.ensure_blas
    except (ImportError, AttributeError):
        return False

    def installed() -> None:
        if importlib.util.find_spec("scipy.linalg") is None:
            raise ImportError("scipy.linalg is not installed")

    nl.ensure_blas = installed
    try:
        import numba.np.arraymath  # noqa: F401  (the import is the point)
    except Exception:   # pragma: no cover - a numba that differs: it imports it itself later
        return False
    finally:
        nl.ensure_blas = real
    return True

