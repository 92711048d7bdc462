"""The one overwrite rule of the commands that write derived outputs.

``fuse``, ``evaluate``, ``resample``, ``rgb`` and ``export`` refuse to replace
outputs that already exist unless ``--force`` is given (raw captures are never
replaced, with or without it). ``build`` is the exception by design: an
existing dataset is resumed or extended, and scenes whose inputs and parameters
are unchanged are kept (its ``--force`` rebuilds them).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from mehs.errors import InputError

FORCE_HELP = "replace outputs that already exist (refused without it)"


def refuse_existing(paths: Iterable[str | Path], force: bool) -> None:
    """Raise :class:`InputError` naming the first existing path of ``paths`` unless ``force``.

    Call it before any work, so that a refusal costs nothing.
    """
    if force:
        return
    existing = [Path(p) for p in paths if Path(p).exists()]
    if existing:
        more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
        raise InputError(f"output exists{more}; use --force to replace it", existing[0])
