"""Atomic writes and file hashing.

Every file mehs writes goes to a temporary name in the destination folder and
is renamed into place only when complete, so a crash never leaves a partial
file that looks finished. Raw captures are never overwritten.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

from mehs.errors import InputError



def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# mkstemp creates files 0600; outputs are ordinary data files, so give them the
# permissions a plain open() would have given.
_FILE_MODE = 0o666 & ~_umask()


def _mkdir(folder: Path, target: Path) -> None:
    """Create ``folder`` (and parents) for ``target``; :class:`InputError` if impossible."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        # name the culprit: usually a file standing where a folder is needed
        blocker = next((a for a in [folder, *folder.parents] if a.exists() and not a.is_dir()),
                       None)
        why = (f"{blocker} is a file, not a folder" if blocker is not None
               else f"cannot create the folder {folder} ({exc.strerror or exc})")
        raise InputError(why, target) from None


@contextlib.contextmanager
def atomic_path(path: str | Path, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The temporary file keeps the destination's suffix (some writers, e.g.
    OpenEXR, look at it). On an exception the temporary file is removed and
    ``path`` is left untouched.

    Parameters
    ----------
    overwrite
        If ``False`` and ``path`` exists, raise :class:`InputError` instead of
        replacing it (used for raw captures).
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise InputError("refusing to overwrite an existing file", path)
    _mkdir(path.parent, path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix,
                                   dir=path.parent)
    except OSError as exc:
        _name_target(exc, path)
        raise
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not overwrite and path.exists():
            raise InputError("refusing to overwrite an existing file", path)
        if tmp_path.is_file():
            os.chmod(tmp_path, _FILE_MODE)
            # the data must be on disk before the name: ext4/xfs may commit a rename
            # before the delayed data blocks, and after a power loss a new name then
            # holds a zero-length or truncated file that looks complete
            _fsync_file(tmp_path)
        if overwrite or not _link_no_clobber(tmp_path, path):
            os.replace(tmp_path, path)
        _fsync_dir(path.parent)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        if isinstance(exc, OSError):
            _name_target(exc, path)
        raise


def _link_no_clobber(tmp: Path, path: Path) -> bool:
    """Give ``tmp`` the name ``path`` only if ``path`` does not exist, in one step.

    The existence check before ``os.replace`` leaves a window in which another writer's
    file (a raw capture) can appear and be replaced; ``link`` fails instead. Returns False
    where hard links are not supported (FAT, some network shares): the caller renames,
    after the check.
    """
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise InputError("refusing to overwrite an existing file", path) from None
    except OSError as exc:
        if exc.errno in (errno.EPERM, errno.EXDEV, errno.EMLINK, errno.ENOTSUP,
                         errno.EOPNOTSUPP, errno.ENOSYS):
            if path.exists():
                raise InputError("refusing to overwrite an existing file", path) from None
            return False
        raise
    tmp.unlink()
    return True


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable; best effort (some file systems refuse it)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def unlink_durable(path: str | Path) -> bool:
    """Remove ``path`` (if present) and make the removal durable; True if it was there.

    For a commit point (a summary, a header) that must be gone before the files it
    described are replaced: without the directory ``fsync`` a power loss could bring the
    old commit point back beside new files.
    """
    path = Path(path)
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    _fsync_dir(path.parent)
    return True


def _name_target(exc: OSError, path: Path) -> None:
    """Make ``exc`` name ``path`` when it names no file, or only the temporary one.

    A failed write (ENOSPC, EIO) carries no file name, and a failed mkstemp or
    rename names the hidden ``.<name>.*.part*`` file, which the user never asked
    for and which is gone when the message is read.
    """
    name = (Path(os.fsdecode(exc.filename)).name
            if isinstance(exc.filename, (str, bytes, os.PathLike)) else None)
    if name is None or (name.startswith(f".{path.name}.") and ".part" in name):
        exc.filename, exc.filename2 = str(path), None


def write_bytes_atomic(path: str | Path, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically and return the path."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str, *, overwrite: bool = True) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically and return the path."""
    return write_bytes_atomic(path, text.encode("utf-8"), overwrite=overwrite)


def write_json_atomic(path: str | Path, obj: Any, *, overwrite: bool = True) -> Path:
    """Write ``obj`` as indented, key-sorted JSON to ``path`` atomically."""
    text = json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n"
    return write_text_atomic(path, text, overwrite=overwrite)


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes.

    ``hashlib.file_digest`` reads into one reused buffer: reading 4 MiB ``bytes``
    at a time allocated fresh memory for every block, and hashing a 512² scene's
    537 MB took 1.09 s instead of 0.40 s (issue 16; the check runs beside every fusion).
    """
    with open(path, "rb") as fh:
        if hasattr(hashlib, "file_digest"):          # Python >= 3.11
            return hashlib.file_digest(fh, "sha256").hexdigest()
        h = hashlib.sha256()
        buf = bytearray(1 << 18)
        view = memoryview(buf)
        while n := fh.readinto(buf):
            h.update(view[:n])
        return h.hexdigest()


def sha256_files(paths: Mapping[str, str | Path], *, threads: int | None = None
                 ) -> dict[str, str]:
    """``{name: hex SHA-256}`` of the files ``paths`` (``{name: path}``), several at a time.

    One file's SHA-256 is a sequential chain, but hashlib releases the GIL while it
    hashes: a scene's three 107 MB exposures took 0.26 s one after another on this
    project's 2-core machine, where each core hashes ~1.7 GB/s (issue 16). The largest
    files go first, on ``threads`` threads (default: the CPUs this process may use), so
    that a big one does not start last. An error (a file that cannot be read) is raised
    as :func:`sha256_file` raises it, for the first such file in ``paths``' order, once
    the hashes running then have ended (a path that is missing or not a regular file
    goes first).
    """
    items = list(paths.items())
    if threads is None:
        try:
            threads = len(os.sched_getaffinity(0))
        except AttributeError:      # not Linux
            threads = os.cpu_count() or 1
    threads = max(1, min(int(threads), len(items)))
    if threads == 1:
        return {name: sha256_file(p) for name, p in items}
    from concurrent.futures import ThreadPoolExecutor

    def key(i: int) -> tuple[int, int]:
        try:
            st = os.stat(items[i][1])
        except OSError:             # first: raised again, with its name, by its hash
            return 0, 0
        # a folder, a device: first too (its hash fails, or is no file's)
        return (1, -st.st_size) if stat.S_ISREG(st.st_mode) else (0, 0)

    with ThreadPoolExecutor(threads, thread_name_prefix="mehs-sha256") as pool:
        futures = {i: pool.submit(sha256_file, items[i][1])
                   for i in sorted(range(len(items)), key=key)}
        try:
            return {items[i][0]: futures[i].result() for i in range(len(items))}
        except BaseException:
            # no file hashed after the error is known (the pool waits for those running)
            for f in futures.values():
                f.cancel()
            raise


def check_output_dir(path: str | Path, *, inputs=()) -> Path:
    """``path`` as a Path if it can be an output folder, else :class:`InputError`.

    Refuses an existing non-folder (``mkdir`` would raise a bare
    ``FileExistsError``) and a folder equal to, or inside, one of the input
    folders ``inputs`` (outputs must never be mixed into raw captures). Creates
    nothing, so callers can check before a long computation.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError("output folder exists and is not a folder", path)
    existing = next((a for a in path.parents if a.exists()), None)
    if existing is not None and not existing.is_dir():
        raise InputError(f"{existing} is a file, not a folder", path)
    target = path.resolve()
    for inp in inputs:
        src = Path(inp).resolve()
        if src.is_dir() and (target == src or src in target.parents):
            raise InputError(f"output folder is inside the input {inp}; "
                             "give an --out outside the inputs", path)
    refuse_inside_raw_capture(path)
    return path


def raw_capture_containing(path: str | Path) -> Path | None:
    """The raw capture folder (Specim IQ layout, or a mehs scene with ``scene.json``) that
    ``path`` is, or lies inside, or None."""
    from mehs.io.specim import is_specim_folder

    target = Path(path).resolve()
    for anc in [target, *target.parents][:6]:
        if anc.is_dir() and ((anc / "scene.json").is_file() or is_specim_folder(anc)):
            return anc
    return None


def refuse_inside_raw_capture(path: str | Path) -> None:
    """Raise :class:`InputError` when ``path`` would be written into a raw capture folder.

    Raw captures are never written into: an ENVI output there may replace a raw
    cube's header and remove its data file (a rewrite drops the old pair's data
    of another extension), and even a new file changes the capture's contents.
    """
    cap = raw_capture_containing(path)
    if cap is not None:
        raise InputError(f"output lies inside the raw capture {cap}; raw captures are never "
                         "written into — choose an output outside it", path)


def make_output_dir(path: str | Path, *, inputs=()) -> Path:
    """:func:`check_output_dir`, then create the folder (and its parents)."""
    path = check_output_dir(path, inputs=inputs)
    _mkdir(path, path)
    return path
