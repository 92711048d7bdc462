"""Replace a folder by a complete new one, never leaving half a folder or none.

A folder of outputs (the images of ``mehs report``) is written under a temporary
name beside its destination and put in place only when complete. On Linux the
two names are exchanged in one step (``renameat2(RENAME_EXCHANGE)``, Linux ≥ 3.15,
glibc ≥ 2.28, on file systems that support it: ext4, xfs, btrfs, tmpfs): at no
instant is the destination missing. Elsewhere the previous folder is renamed
aside and the new one renamed in — two steps, with the previous folder put back if
the second one fails or is interrupted.

References
----------
renameat2(2), Linux man-pages: ``RENAME_EXCHANGE``.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from mehs.errors import MehsError

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def remove_path(path: str | Path, what: str = "leftover") -> None:
    """Remove ``path`` whatever it is (folder tree, file, symbolic link); nothing if absent.

    Raises
    ------
    MehsError
        When it cannot be removed (the message names it and says what it is).
    """
    path = Path(path)
    try:
        if path.is_symlink() or path.is_file():
            path.unlink()
        elif path.is_dir():
            shutil.rmtree(path)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise MehsError(f"cannot remove the {what} ({exc.strerror or exc}); remove it by hand",
                        path) from None


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` atomically; False where the system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # glibc < 2.28, musl without it
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    # any failure (EINVAL on a file system without exchange, ENOSYS in a sandbox) falls
    # back to the two renames, which name the path in their own error if it is real
    return fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def replace_folder(new: str | Path, dest: str | Path) -> None:
    """Put the complete folder ``new`` at ``dest``; the previous ``dest`` (if any) is removed
    only after ``new`` is in place.

    Parameters
    ----------
    new
        The finished folder, on the same file system as ``dest`` (beside it).
    dest
        Where it goes. A ``<dest>.old`` beside it is used on systems without an atomic
        exchange (and removed); an interrupted swap there leaves either the previous
        folder at ``dest`` or, between the two renames, puts it back.
    """
    new, dest = Path(new), Path(dest)
    old = dest.with_name(dest.name + ".old")
    if dest.exists() and _exchange(new, dest):
        _discard(new)  # it now holds the previous contents
        _discard(old)  # a two-rename swap killed while it removed the previous folder
        return
    remove_path(old)
    moved = False
    try:
        if dest.exists() or dest.is_symlink():
            os.rename(dest, old)
            moved = True
        os.rename(new, dest)
    except BaseException:
        if moved and not dest.exists():
            os.rename(old, dest)
        raise
    _discard(old)


def _discard(previous: Path) -> None:
    """Remove the previous contents once the new folder is in place; a failure is a
    warning, not an error: the swap is done, and what uses the new folder goes on."""
    import warnings

    try:
        remove_path(previous, "previous folder")
    except MehsError as exc:
        warnings.warn(f"{exc}; the new folder is in place", RuntimeWarning, stacklevel=3)
