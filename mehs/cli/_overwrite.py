"""The one overwrite rule of the commands that write derived outputs.

``fuse``, ``evaluate``, ``resample``, ``rgb`` and ``export`` refuse to replace
outputs that already exist unless ``--force`` is given (raw captures are never
replaced, with or without it). ``build`` is the exception by design: an
existing dataset is resumed or extended, and scenes whose inputs and parameters
are unchanged are kept (its ``--force`` rebuilds them).

Two checks every writing command makes before any work: :func:`check_writable` (a
folder the user may not write into is named before a capture moves the stage or a
build starts its workers, not through a temporary file's name afterwards) and
:func:`refuse_foreign_folder` (an ``--out`` that already holds other files — a typo,
the wrong folder — is refused instead of having outputs mixed into it).
"""

from __future__ import annotations

import os
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


def check_writable(path: str | Path) -> None:
    """Raise :class:`InputError` when ``path`` (a file or folder to create or write into)
    cannot be written: its nearest existing folder is not writable by this user."""
    p = Path(path)
    existing = next((a for a in (p, *p.parents) if a.exists()), None)
    if existing is None or not existing.is_dir():
        return  # check_output_dir names a file in the way
    if not os.access(existing, os.W_OK | os.X_OK):
        where = "" if existing == p else f" (in {existing})"
        raise InputError(f"cannot write here{where}: permission denied", p)


def _ours(name: str, own: frozenset[str]) -> bool:
    # a hidden lock or temporary file of an earlier (perhaps killed) mehs run is ours too
    return name in own or name.startswith(".mehs") or name.endswith(".part") or ".part-" in name


def refuse_foreign_folder(path: str | Path, own: Iterable[str], *, force: bool | None = False,
                          what: str = "outputs") -> None:
    """Raise :class:`InputError` when ``path`` is an existing folder that holds files but
    none of this command's (``own``: the names it writes).

    Such a folder is someone else's — a mistyped ``--out``, a capture or a project folder —
    and the outputs would be mixed into it. A folder of this command's earlier outputs is
    left to the overwrite rule (:func:`refuse_existing`); ``force`` writes beside other
    files (``None``: the command has no ``--force``). Hidden files (``.DS_Store``,
    ``.gitkeep``) do not count.
    """
    p = Path(path)
    if force or not p.is_dir():
        return
    from mehs.io.atomic import raw_capture_containing

    if raw_capture_containing(p) is not None:
        return  # refuse_inside_raw_capture says what it is: never written into, even --force
    names = [e.name for e in p.iterdir()]
    own = frozenset(own)
    if any(_ours(n, own) for n in names):
        return
    visible = sorted(n for n in names if not n.startswith("."))
    if visible:
        shown = ", ".join(visible[:3]) + (f", … ({len(visible)} entries)" if len(visible) > 3 else "")
        hint = "" if force is None else " (or --force to write beside them)"
        raise InputError(f"output folder exists and holds other files, not {what} ({shown}); "
                         f"give a new or empty folder{hint}", p)
