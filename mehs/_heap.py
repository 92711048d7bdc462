"""glibc's heap thresholds (``mallopt``) and ``malloc_trim``, where the C library is glibc.

Used by ``mehs fuse`` (:func:`mehs.cli.reuse_heap`) and tiled SSR inference
(:func:`mehs.ssr.allocator.reused_heap`): on a VM where first touching memory is
expensive, keeping freed blocks on the heap instead of unmapping them saves the
faults of every later array of that size (issue 16). Elsewhere everything is a no-op.
"""

from __future__ import annotations

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

_LIBC: list = []


def _libc():
    if not _LIBC:
        fns = None
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6")
            trim, mallopt = libc.malloc_trim, libc.mallopt
            trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
            mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            fns = (trim, mallopt)
        except (OSError, AttributeError):      # not glibc
            pass
        _LIBC.append(fns)
    return _LIBC[0]


def available() -> bool:
    """Whether the thresholds can be set here (glibc)."""
    return _libc() is not None


def set_thresholds(mmap_bytes: int, trim_bytes: int) -> bool:
    """Serve blocks below ``mmap_bytes`` from the heap; return free heap memory to the
    system only above ``trim_bytes`` at its top. (Setting them ends glibc's dynamic
    adjustment.) True if set."""
    fns = _libc()
    if fns is None:
        return False
    return bool(fns[1](_M_MMAP_THRESHOLD, int(mmap_bytes))) and bool(
        fns[1](_M_TRIM_THRESHOLD, int(trim_bytes)))


def trim() -> None:
    """Return the heap's free memory to the system (``malloc_trim(0)``)."""
    fns = _libc()
    if fns is not None:
        fns[0](0)
