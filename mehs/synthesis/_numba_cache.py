"""A one-line notice when numba is about to compile a kernel that its cache does not hold.

A first-ever ``mehs fuse`` spends seconds compiling the synthesis kernels (cached
afterwards, then well under a second to load); without a word it looks like a
hang (issue 16).
"""

from __future__ import annotations

import os
import sys


def notice_if_uncached(dispatcher, what: str = "the merge kernels") -> bool:
    """Print the notice to stderr when ``dispatcher``'s cache index is missing; True if printed.

    Reads numba's cache location (``NUMBA_CACHE_DIR`` or ``__pycache__`` next to
    the source) from the dispatcher; internals, so any surprise means no notice.
    """
    global _told
    if _told:
        return False
    try:
        index = dispatcher._cache._cache_file._index_path
    except AttributeError:
        return False
    if os.path.exists(index):
        return False
    return notice_compiling(what, "numba's cache")


def notice_compiling(what: str, where: str = "the mehs cache") -> bool:
    """Print the one-line compile notice (once per process); True if printed."""
    global _told
    if _told:
        return False
    print(f"mehs: compiling {what} once (a few seconds); later runs load them from {where}",
          file=sys.stderr)
    _told = True
    return True


_told = False


#: The kernel modules whose numba functions inline each other's (``inline="always"``, and
#: LLVM-inlined helpers): numba's cache checks only the source file of the function it
#: compiled, so an edit to ``_merge_rows.py`` alone left ``_merge_kernels``' cached
#: machine code in use — the old arithmetic, silently (an editable install after a
#: ``git pull``). :func:`drop_stale_kernel_caches` keys them on all their sources.
KERNEL_MODULES = ("_cephes", "_merge_rows", "_merge_kernels", "_merge_fused",
                  "_merge_fused_weighted", "_merge_binned", "_merge_binned_weighted",
                  "_ptc_kernels")
_STAMP = "mehs-kernel-sources.sha256"
_checked = False


def drop_stale_kernel_caches() -> None:
    """Remove numba's cached kernels of :data:`KERNEL_MODULES` when any of their sources
    changed since they were cached (once per process; before any of them loads)."""
    global _checked
    if _checked:
        return
    _checked = True
    import hashlib
    from pathlib import Path

    here = Path(__file__).resolve().parent
    try:
        h = hashlib.sha256()
        for m in KERNEL_MODULES:
            h.update((here / f"{m}.py").read_bytes())
        digest = h.hexdigest()
        from numba.core.caching import CacheImpl
    except (OSError, ImportError):
        return

    def _probe():
        pass

    # the modules share one folder, so numba's first usable locator (its own order) gives
    # one cache folder for all of them
    dirs = []
    for cls in CacheImpl._locator_classes:
        try:
            loc = cls.from_function(_probe, str(here / f"{KERNEL_MODULES[0]}.py"))
        except Exception:                           # noqa: BLE001 - a locator numba would skip
            loc = None
        if loc is not None:
            dirs.append(Path(loc.get_cache_path()))
            break
    for d in dirs:
        stamp = d / _STAMP
        try:
            if stamp.read_text().strip() == digest:
                continue
        except OSError:
            pass
        try:
            for f in d.iterdir():
                if f.suffix in (".nbi", ".nbc") and f.name.split(".")[0] in KERNEL_MODULES:
                    f.unlink(missing_ok=True)
            tmp = d / f".{_STAMP}.{os.getpid()}"
            tmp.write_text(digest + "\n")
            os.replace(tmp, stamp)
        except OSError:
            continue
