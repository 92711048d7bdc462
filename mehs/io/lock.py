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
"""

from __future__ import annotations

import contextlib
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
        self._created: list[Path] = []

    def __enter__(self) -> "OutputLock":
        # the folders this creates (--out and missing parents), innermost first
        self._created = [d for d in (self.folder, *self.folder.parents) if not d.exists()]
        self.folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f"{self.path.name}.", suffix=".part", dir=self.folder)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(f"{os.getpid()} {os.uname().nodename} {self.what}\n")
            for _ in range(2):
                try:
                    os.link(tmp, self.path)
                except FileExistsError:
                    if self._stale():
                        with contextlib.suppress(FileNotFoundError):
                            self.path.unlink()
                        continue
                    holder = self._holder()
                    raise InputError(f"another {holder} is writing this folder (lock "
                                     f"{self.path.name}); wait for it, or remove the lock if "
                                     "that process is dead", self.folder) from None
                self._mine = True
                self._remove_leftovers()
                return self
            raise InputError("could not take the output folder's lock", self.path)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)

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
        return f"'{' '.join(f[2:])}' (pid {f[0]})" if len(f) >= 3 else "mehs command"

    def _stale(self) -> bool:
        f = self._fields()
        try:
            pid, host = int(f[0]), f[1]
        except (IndexError, ValueError):
            return True          # written complete before it appears: garbage is no writer's
        if host != os.uname().nodename:
            return False         # another machine's process: cannot tell, keep it
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
                self.path.unlink()
            self._mine = False
            if exc_type is not None:
                # a write refused before its first file leaves no empty --out behind
                for d in self._created:
                    try:
                        d.rmdir()
                    except OSError:
                        break
