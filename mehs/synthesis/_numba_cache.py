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


_locator_added = False


def ensure_cache_locator() -> bool:
    """Give numba a cache folder for mehs's kernels where it has none of its own.

    numba caches a ``cache=True`` function in ``__pycache__`` beside its source, else in
    ``~/.cache/numba``; with neither writable — mehs installed by root in a container
    image and run by a user without a home folder — it refused to decorate the kernels:
    ``import mehs.synthesis._cephes`` raised "cannot cache function 'logf': no locator
    available", and every fusion with it. A last locator is appended to numba's list,
    for the files of this folder only (other code's caching is untouched, and numba's
    own locators keep precedence): the mehs cache folder's ``numba/`` (whose default
    place falls back to a private temporary folder, :func:`mehs._cache.cache_dir`), or
    with ``MEHS_CACHE_DIR`` empty the private temporary folder's. numba internals:
    anything unexpected leaves numba as it is. True if the locator is (now) in place.
    """
    global _locator_added
    if _locator_added:
        return True
    try:
        from numba.core import caching

        classes = caching.CacheImpl._locator_classes
        base = getattr(caching, "UserProvidedCacheLocator", None) \
            or caching._UserProvidedCacheLocator
    except (ImportError, AttributeError):
        return False
    here = os.path.dirname(os.path.realpath(__file__))

    class MehsFallbackLocator(base):
        """numba's locator of a user-provided folder, answering for mehs's kernels only
        and choosing its folder itself (not ``NUMBA_CACHE_DIR``)."""

        def __init__(self, py_func, py_file, root):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = os.path.join(root, self.get_suitable_cache_subpath(py_file))

        @classmethod
        def from_function(cls, py_func, py_file):
            if (not os.path.exists(py_file)
                    or os.path.dirname(os.path.realpath(py_file)) != here):
                return None
            from mehs._cache import cache_dir, private_temp_dir

            for where in (cache_dir, private_temp_dir):     # the second only if needed
                root = where()
                if root is None:
                    continue
                self = cls(py_func, py_file, str(root / "numba"))
                try:
                    self.ensure_cache_path()
                except OSError:
                    continue
                return self
            return None

    if not any(c.__name__ == "MehsFallbackLocator" for c in classes):
        classes.append(MehsFallbackLocator)
    _locator_added = True
    return True


def drop_stale_kernel_caches() -> None:
    """Remove numba's cached kernels of :data:`KERNEL_MODULES` when any of their sources
    changed since they were cached (once per process; before any of them loads)."""
    global _checked
    if _checked:
        return
    _checked = True
    ensure_cache_locator()
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
