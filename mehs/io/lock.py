"""An exclusive lock file in an output folder, so that two commands never write one folder.

Two ``mehs fuse`` runs into one ``--out`` both pass the "output exists" check at
their start and then write file by file: the folder ended with one run's radiance
and the other's summary, complete-looking and wrong. The commands that write a
folder hold :class:`OutputLock` while they write it; a second writer is refused
with a message naming the holder. A lock left by a dead process (same host, pid
gone) is taken over.

The lock file is made complete before it appears (written under a temporary
name, then hard-linked to the lock name, which fails if the lock exists), so a
reader never sees an empty lock and never takes a live writer's lock for stale.
Taking the lock removes the temporary files a killed writer left in the folder.

Whether the holder lives is the kernel's answer, not the pid's: the holder keeps an
``flock`` on the lock file, which the kernel releases when the process dies however it
dies (SIGKILL, OOM killer), and which no process holds after a power loss. A pid alone
could not tell: after a reboot, or in another PID namespace, a killed writer's pid is
often some live process's, and its lock was then never taken over. A stale lock is
taken over only while this process holds that lock file's ``flock`` and the lock name
still names that file, so two processes recovering one stale lock at once never both
hold the folder (each used to unlink "the stale lock", which by then could be the
other's new one). On a file system without ``flock`` (some network mounts) the pid and
host in the lock decide, as before.

References
----------
flock(2), link(2) — Linux man-pages.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import tempfile
from pathlib import Path

from mehs.errors import InputError

__all__ = ["OutputLock", "LOCK_NAME"]

#: what :func:`mehs.io.atomic.atomic_path` names its temporary files (``.<name>.<random>.part<ext>``)
_PART = re.compile(r"\..+\.part(\.[^./]*)?")

#: the lock of an output folder (a dataset's is its build lock)
LOCK_NAME = ".mehs-write.lock"


class OutputLock:
    """Context manager: hold ``folder/name`` while writing ``folder`` (created if needed)."""

    def __init__(self, folder: str | Path, *, name: str = LOCK_NAME, what: str = "mehs"):
        self.folder = Path(folder)
        self.path = self.folder / name
        self.what = what
        self._mine = False
        self._fd = -1
        self._created: list[Path] = []

    def __enter__(self) -> "OutputLock":
        # the folders this creates (--out and missing parents), innermost first
        self._created = [d for d in (self.folder, *self.folder.parents) if not d.exists()]
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f"{self.path.name}.", suffix=".part", dir=self.folder)
        try:
            os.write(fd, f"{os.getpid()} {os.uname().nodename} {self.what}\n".encode())
            # held from before the name appears: no instant at which the lock looks unowned
            _try_flock(fd)
            for _ in range(8):
                try:
                    os.link(tmp, self.path)
                except (FileExistsError, FileNotFoundError) as exc:
                    # FileNotFoundError: a holder's clean-up took this temporary for a killed
                    # writer's (only a holder cleans up): the folder is taken
                    if isinstance(exc, FileExistsError) and self._take_over_stale():
                        continue
                    holder = self._holder()
                    raise InputError(f"another {holder} is writing this folder (lock "
                                     f"{self.path.name}); wait for it, or remove the lock if "
                                     "that process is dead", self.folder) from None
                self._fd, fd = fd, -1
                self._mine = True
                self._remove_leftovers()
                return self
            raise InputError("could not take the output folder's lock", self.path)
        finally:
            if fd >= 0:
                os.close(fd)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)

    def _take_over_stale(self) -> bool:
        """Remove the lock file if its holder is dead; True when the name is free now
        (or was changed by another process meanwhile: look again)."""
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return True                   # released meanwhile
        try:
            held = _try_flock(fd)
            if held is False:
                return False              # a live process holds it
            if not self._stale(ask_pid=held is None):
                return False              # another host's (a mount may keep flocks local)
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                return True
            if same:
                # while this process holds the flock of that very file, no other taker can
                # have replaced it: the unlink removes the dead holder's lock, never a new one
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
            return True
        finally:
            os.close(fd)

    def _remove_leftovers(self) -> None:
        # temporary files of a writer killed here before its rename (hidden, ".part"): only
        # the lock holder writes this folder, so none of them belongs to a live write
        for f in self.folder.iterdir():
            if _PART.fullmatch(f.name) and f.is_file():
                with contextlib.suppress(OSError):
                    f.unlink()

    def _fields(self) -> list[str]:
        try:
            return self.path.read_text().split()
        except OSError:
            return []

    def _holder(self) -> str:
        f = self._fields()
        if len(f) < 3:
            return "mehs command"
        where = "" if f[1] == os.uname().nodename else f" on host {f[1]}"
        return f"'{' '.join(f[2:])}' (pid {f[0]}{where})"

    def _stale(self, *, ask_pid: bool = True) -> bool:
        """Whether the lock's holder is dead, from the pid and host it wrote.

        Another host's lock is kept (its pid cannot be asked, and a network mount may keep
        ``flock`` local to each host); a same-host pid is asked only where no ``flock``
        answered (``ask_pid``): a live pid may be a reused one.
        """
        f = self._fields()
        try:
            pid, host = int(f[0]), f[1]
        except (IndexError, ValueError):
            return True          # written complete before it appears: garbage is no writer's
        if host != os.uname().nodename:
            return False         # another machine's process: cannot tell, keep it
        if not ask_pid:
            return True
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            return False         # exists, owned by another user
        return False

    def __exit__(self, exc_type, *exc) -> None:
        if self._mine:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()     # before the flock goes: a taker then sees no file
            os.close(self._fd)
            self._fd = -1
            self._mine = False
            if exc_type is not None:
                # a write refused before its first file leaves no empty --out behind
                for d in self._created:
                    try:
                        d.rmdir()
                    except OSError:
                        break


def _try_flock(fd: int) -> bool | None:
    """Take an exclusive ``flock`` on ``fd`` without waiting: True taken, False held by a
    live process, None when this file system (or platform) has no such locks."""
    try:
        import fcntl
    except ImportError:                       # Windows
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        return None                           # ENOLCK, EOPNOTSUPP, EINVAL: no locks here
    return True
