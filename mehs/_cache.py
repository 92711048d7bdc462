"""Where mehs keeps what it can measure or compile once: ``MEHS_CACHE_DIR``.

Used by the tiling probes (:mod:`mehs.ssr.probe_cache`), the merge kernels' machine
code (:mod:`mehs.synthesis._native`) and, where numba has nowhere of its own, numba's
cache of the kernels (:mod:`mehs.synthesis._numba_cache`). ``MEHS_CACHE_DIR`` if set
(empty: no cache), else ``$XDG_CACHE_HOME/mehs`` or ``~/.cache/mehs``; when that default
place cannot be created or written — a container's user without a home folder, a
read-only home — a private folder in the temporary directory (:func:`private_temp_dir`).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


def cache_dir() -> Path | None:
    """The mehs cache folder, or None when ``MEHS_CACHE_DIR`` is set empty or neither the
    default place nor a private temporary folder can hold one: nothing is kept.

    A folder named by ``MEHS_CACHE_DIR`` is returned as named (created when something is
    stored). The default place is created here, and replaced by :func:`private_temp_dir`
    when it cannot be: without it every process in such a container compiled the
    synthesis kernels afresh (seconds each) and ran the scalar ones of numba's own build.
    """
    env = os.environ.get("MEHS_CACHE_DIR")
    if env is not None:
        return Path(env).expanduser() if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except (RuntimeError, KeyError, OSError):
            base = None
    if base:
        folder = Path(base) / "mehs"
        if writable_folder(folder):
            return folder
    return private_temp_dir()


def writable_folder(folder: Path) -> bool:
    """Whether files can be stored in ``folder`` (created, with its parents, if missing)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)


def private_temp_dir() -> Path | None:
    """``<temp>/mehs-cache-<uid>``, created with mode 0700, or None when it cannot be
    trusted.

    It holds machine code and pickles that later processes load, and the temporary
    directory is shared by every user of the machine: the folder is used only if it is
    a real folder (not a link), owned by this user and writable by no one else — one
    that another user made first is refused, not adopted. (On Windows the temporary
    directory is the user's own.)
    """
    import tempfile     # (here: ~ms of imports that most calls never need)

    uid = os.getuid() if hasattr(os, "getuid") else None
    name = "mehs-cache" if uid is None else f"mehs-cache-{uid}"
    folder = Path(tempfile.gettempdir()) / name
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        st = folder.lstat()
    except OSError:
        return None
    if not stat.S_ISDIR(st.st_mode):
        return None
    if uid is not None and (st.st_uid != uid or st.st_mode & 0o022):
        return None
    if not os.access(folder, os.W_OK | os.X_OK):
        return None
    return folder
