"""Where mehs keeps what it can measure or compile once: ``MEHS_CACHE_DIR``.

Used by the tiling probes (:mod:`mehs.ssr.probe_cache`) and the merge kernels' machine
code (:mod:`mehs.synthesis._native`). ``MEHS_CACHE_DIR`` if set (empty: no cache),
else ``$XDG_CACHE_HOME/mehs`` or ``~/.cache/mehs``.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path | None:
    """The mehs cache folder, or None when ``MEHS_CACHE_DIR`` is set empty or there is
    no home folder to put it in (a container's user without one): nothing is kept."""
    env = os.environ.get("MEHS_CACHE_DIR")
    if env is not None:
        return Path(env).expanduser() if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except (RuntimeError, KeyError, OSError):
            return None
    return Path(base) / "mehs"
