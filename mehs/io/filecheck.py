"""Check files against the SHA-256 a manifest recorded for them, cheaply when possible.

Hashing a dataset before every reuse or evaluation would cost a full read of
every file. A writer therefore also records each file's ``[size, mtime_ns]``
(its *stat*); a reader trusts a file whose stat is unchanged, and hashes it in
full only when the stat differs (a copied, touched or altered file) or when
asked to (``full=True``, the ``--verify`` options). A size that differs from
the recorded one needs no hash at all: the file is damaged.

The stat is a cache, not a guarantee: a file altered in place with its mtime
restored passes the cheap check; ``full=True`` catches that too.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

from mehs.errors import FormatError
from mehs.io.atomic import sha256_file

#: ``(absolute path, size, mtime_ns) -> sha256`` of files hashed by this process, so that
#: one command listing a dataset several times hashes a changed-stat file once.
_HASHED: dict[tuple[str, int, int], str] = {}


def file_stat(path: str | Path) -> list[int]:
    """``[size, mtime_ns]`` of ``path`` (what :func:`verify_files` compares cheaply)."""
    st = os.stat(path)
    return [int(st.st_size), int(st.st_mtime_ns)]


def verify_files(root: str | Path, files: Mapping[str, str], sha256: Mapping[str, str], *,
                 stats: Mapping[str, list[int]] | None = None, full: bool = False,
                 what: str = "", manifest: str = "manifest.json") -> dict[str, list[int]]:
    """Check that each file of ``files`` still has the SHA-256 recorded in ``sha256``.

    Parameters
    ----------
    root
        Folder the relative paths of ``files`` are relative to.
    files
        ``{name: relative path}``.
    sha256
        ``{name: hex digest}`` recorded when the files were written.
    stats
        ``{relative path: [size, mtime_ns]}`` recorded with the hashes, or None.
        A file whose stat equals its record is not hashed (unless ``full``).
    full
        Hash every file whatever its stat.
    what
        Prefix of error messages (e.g. ``"scene 'a'"``).
    manifest
        Name of the record, for messages.

    Returns
    -------
    dict
        ``{relative path: [size, mtime_ns]}`` of every checked file, as found now
        (a caller may store it to make the next check cheap).

    Raises
    ------
    FormatError
        Naming the file: missing, without a recorded hash, of another size, or
        with another SHA-256.
    """
    root = Path(root)
    stats = stats if isinstance(stats, Mapping) else {}
    prefix = f"{what}: " if what else ""
    fresh: dict[str, list[int]] = {}
    for name, rel in sorted(files.items()):
        if not isinstance(rel, str) or not rel:
            raise FormatError(f"{prefix}'{name}' has no file path in {manifest} (damaged "
                              "entry); rebuild the scene", root / manifest)
        path = root / rel
        digest = sha256.get(name)
        if not isinstance(digest, str):
            raise FormatError(f"{prefix}{rel} has no recorded SHA-256 in {manifest} (damaged "
                              "entry); rebuild the scene", path)
        try:
            now = file_stat(path)
        except FileNotFoundError:
            raise FormatError(f"{prefix}{rel} listed in {manifest} is missing", path) from None
        old = stats.get(rel)
        if not (isinstance(old, (list, tuple)) and len(old) == 2
                and all(isinstance(v, int) for v in old)):
            old = None  # a damaged record is no cache: hash the file
        if old is not None and list(old)[0] != now[0]:
            raise FormatError(f"{prefix}{rel} has {now[0]} bytes, {old[0]} when it was "
                              f"written (truncated or altered)", path)
        if full or old is None or list(old) != now:
            memo = (str(path.resolve()), now[0], now[1])
            got = _HASHED.get(memo) if not full else None
            if got is None:
                got = _HASHED[memo] = sha256_file(path)
            if got != digest:
                raise FormatError(f"{prefix}{rel} does not match its SHA-256 in {manifest} "
                                  "(file altered or damaged)", path)
        fresh[rel] = now
    return fresh


class HashCheck:
    """SHA-256 of files against recorded digests, computed by background threads.

    Started on construction; :meth:`result` waits and raises :class:`FormatError`
    naming the first file (in the given order) whose hash differs or that cannot
    be read. Hashing releases the GIL, so the caller keeps working meanwhile —
    on other files, or on the data of these ones (``mehs fuse`` fuses while the
    raws are hashed, and writes nothing until the check has passed).

    Parameters
    ----------
    items
        ``(path, hex digest)`` pairs.
    message
        The error text for a mismatch.
    threads
        Hashing threads (files are spread over them; one file is never split).
    """

    def __init__(self, items, *, message: str = "SHA-256 does not match its record "
                 "(file altered or truncated)", threads: int = 1) -> None:
        import threading

        self._items = [(Path(p), str(d)) for p, d in items]
        self._message = message
        self._errors: list[FormatError | None] = [None] * len(self._items)
        n = max(1, min(int(threads), len(self._items)))
        # the largest files first, spread round-robin: the threads finish together
        order = sorted(range(len(self._items)), key=lambda i: -_size(self._items[i][0]))
        self._threads = [threading.Thread(target=self._run, args=(order[k::n],), daemon=True,
                                          name=f"mehs-sha256-{k}") for k in range(n)]
        for t in self._threads:
            t.start()

    def _run(self, indices) -> None:
        for i in indices:       # all of them: the first failing file is named, whatever the threads
            path, digest = self._items[i]
            try:
                ok = sha256_file(path) == digest
                err = None if ok else FormatError(self._message, path)
            except OSError as exc:
                err = FormatError(f"cannot be read to check its SHA-256 ({exc.strerror or exc})",
                                  path)
            self._errors[i] = err

    def result(self) -> None:
        """Wait for the check; :class:`FormatError` for the first failing file."""
        for t in self._threads:
            t.join()
        err = next((e for e in self._errors if e is not None), None)
        if err is not None:
            raise err


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
