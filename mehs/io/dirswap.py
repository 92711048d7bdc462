"""Replace a folder by a complete new one, never leaving half a folder or none.

A folder of outputs (the images of ``mehs report``) is written under a temporary
name beside its destination and put in place only when complete. On Linux the
two names are exchanged in one step (``renameat2(RENAME_EXCHANGE)``, Linux ≥ 3.15,
glibc ≥ 2.28, on file systems that support it: ext4, xfs, btrfs, tmpfs): at no
instant is the destination missing. Elsewhere the previous folder is renamed
aside (under the writer's own temporary name) and the new one renamed in — two steps,
with the previous folder put back if the second one fails or is interrupted; when
another writer's folder took the destination between the two steps, it is moved aside
in turn and the swap retried, so concurrent writers each complete there too.

Each writer has its own temporary folder (:func:`make_temp_folder`,
``<dest>.part-<pid>-<host>-<random>``): two runs writing one destination at once
(two ``mehs report`` of one dataset) each swap in a complete folder, the last one
winning, and neither deletes the other's work in progress. What a killed writer left
is removed by the next one (:func:`remove_stale_temp_folders`): a temporary whose
process is gone from this host, or older than :data:`STALE_AFTER_S` (its pid reused,
or another host's, which cannot be asked), and the ``<dest>.part`` of older versions.

References
----------
renameat2(2), Linux man-pages: ``RENAME_EXCHANGE``.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import sys
import time
import zlib
from pathlib import Path

from mehs.errors import MehsError

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2

#: a temporary folder older than this (seconds since its last change) is no live writer's
STALE_AFTER_S = 86400.0


def _host_tag() -> str:
    """8 hex digits naming this host and PID namespace (a pid means something only there:
    containers sharing the host's name have their own pids)."""
    import platform

    ident = platform.node()
    try:
        ident += f"/{os.stat('/proc/self/ns/pid').st_ino}"
    except OSError:
        pass         # no /proc (macOS, Windows): the host name alone
    return f"{zlib.crc32(ident.encode('utf-8')):08x}"


def _temp_re(dest: Path) -> re.Pattern[str]:
    return re.compile(re.escape(dest.name) + r"\.part-(\d+)-([0-9a-f]{8})-[0-9a-z_]+")


def make_temp_folder(dest: str | Path) -> Path:
    """Create and return this process's own new temporary folder beside ``dest``.

    Named ``<dest name>.part-<pid>-<host>-<random>`` (``host``: 8 hex digits of this
    host's name), so that :func:`remove_stale_temp_folders` can tell a live writer's
    from a dead one's. Created with the usual permissions (umask), unlike
    :func:`tempfile.mkdtemp`'s 0700: it becomes the output folder.
    """
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(100):
        tmp = dest.with_name(f"{dest.name}.part-{os.getpid()}-{_host_tag()}-"
                             f"{secrets.token_hex(4)}")
        try:
            tmp.mkdir()
        except FileExistsError:
            continue
        return tmp
    raise MehsError("cannot create a temporary folder (100 names taken)", dest.parent)


def _alive(pid: int) -> bool:
    if os.name == "nt":
        return True          # os.kill(pid, 0) would end it there: the age decides instead
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True          # exists, another user's
    return True


def remove_stale_temp_folders(dest: str | Path, what: str = "unfinished folder",
                              max_age_s: float = STALE_AFTER_S) -> list[Path]:
    """Remove what killed writers left beside ``dest``; never a live writer's folder.

    Removed: ``<dest>.part`` (the one fixed name of older versions, whatever it is) and
    each ``<dest>.part-<pid>-<host>-<random>`` whose process no longer runs on this host,
    or that was last changed more than ``max_age_s`` ago (another host's, whose pid cannot
    be asked; a pid reused since). One that cannot be removed is a warning: it is not in
    the way of a new writer's own folder. Returns the paths removed.
    """
    import warnings

    dest = Path(dest)
    pattern, host, now = _temp_re(dest), _host_tag(), time.time()
    removed = []
    try:
        names = [p.name for p in dest.parent.iterdir()]
    except FileNotFoundError:
        return removed
    for name in names:
        path = dest.parent / name
        m = pattern.fullmatch(name)
        if name != f"{dest.name}.part" and m is None:
            continue
        if m is not None:
            try:
                age = now - path.lstat().st_mtime
            except FileNotFoundError:
                continue     # its writer swapped it in or removed it meanwhile
            pid = int(m.group(1))
            if age <= max_age_s and (m.group(2) != host or _alive(pid)):
                continue     # a live writer's, or another host's that may be
        try:
            remove_path(path, f"{what} of an interrupted run")
        except MehsError as exc:
            warnings.warn(str(exc), RuntimeWarning, stacklevel=2)
            continue
        removed.append(path)
    return removed


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
        Where it goes. On systems without an atomic exchange the previous folder is
        renamed aside under a name of :func:`make_temp_folder`'s pattern (so that what a
        killed swap left is removed like any dead writer's temporary) and removed once
        ``new`` is in place; an interrupted swap puts it back.
    """
    new, dest = Path(new), Path(dest)
    legacy = dest.with_name(dest.name + ".old")   # the one fixed aside name of older versions
    if dest.exists() and _exchange(new, dest):
        _discard(new)  # it now holds the previous contents
        if legacy.exists() or legacy.is_symlink():
            _discard(legacy)  # an older version's two-rename swap, killed mid-way
        return
    remove_path(legacy)
    for attempt in range(_SWAP_TRIES):
        aside = _aside_name(dest)
        moved = False
        try:
            try:
                os.rename(dest, aside)
                moved = True
            except FileNotFoundError:
                pass           # no previous folder (or another writer moved it meanwhile)
            try:
                os.rename(new, dest)
            except OSError as exc:
                # another writer's folder took ``dest`` between the two renames (POSIX:
                # ENOTEMPTY / EEXIST, Windows: FileExistsError): it is the previous folder
                # now; ours goes in on the next try, the last writer winning as on Linux
                if not (dest.exists() and attempt + 1 < _SWAP_TRIES
                        and (isinstance(exc, FileExistsError)
                             or exc.errno in (errno.ENOTEMPTY, errno.EEXIST))):
                    raise
                if moved:
                    _discard(aside)
                continue
        except BaseException:
            if moved and not dest.exists():
                os.rename(aside, dest)
            raise
        if moved:
            _discard(aside)
        return


#: how often the two-rename swap is retried when other writers keep taking the destination
_SWAP_TRIES = 8


def _aside_name(dest: Path) -> Path:
    """A name, unused now, for the previous folder during a two-rename swap: this
    process's temporary pattern (:func:`make_temp_folder`), without creating it."""
    while True:
        aside = dest.with_name(f"{dest.name}.part-{os.getpid()}-{_host_tag()}-"
                               f"{secrets.token_hex(4)}")
        if not (aside.exists() or aside.is_symlink()):
            return aside


def _discard(previous: Path) -> None:
    """Remove the previous contents once the new folder is in place; a failure is a
    warning, not an error: the swap is done, and what uses the new folder goes on."""
    import warnings

    try:
        remove_path(previous, "previous folder")
    except MehsError as exc:
        warnings.warn(f"{exc}; the new folder is in place", RuntimeWarning, stacklevel=3)
