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
