"""ENVI writer: header + data file, atomically, chunk by chunk (see :mod:`mehs.io.envi`).

:func:`write_envi` is re-exported by :mod:`mehs.io.envi`, which reads the files it writes.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.io.atomic import atomic_path
from mehs.io.envi_keys import (INTERLEAVES, MANAGED_KEYS, STRUCTURAL_KEYS,
                               format_acquisition_date)

# Write chunk: big enough that per-chunk overhead vanishes, small enough not to
# duplicate a 100 MB cube in memory.
_CHUNK_BYTES = 16 << 20


def _target_dtype(cube_dtype: np.dtype, dtype: Any) -> np.dtype:
    from spectral.io.envi import dtype_to_envi

    dt = np.dtype(cube_dtype if dtype is None else dtype).newbyteorder("=")
    if dt.char not in dtype_to_envi:
        names = sorted({np.dtype(c).name for c in dtype_to_envi})
        raise InputError(f"data type {dt.name} cannot be stored in ENVI "
                         f"(supported: {', '.join(names)})")
    return dt


def _header_value(key: str, val: Any) -> Any:
    if isinstance(val, np.ndarray):
        val = val.tolist()
    if isinstance(val, (list, tuple)):
        items = [_header_value(key, v) for v in val]
        for it in items:
            if isinstance(it, (list, tuple)) or "," in str(it):
                raise InputError(f"header value of {key!r} cannot hold nested lists "
                                 "or commas inside items")
        return items
    if isinstance(val, (dict, set)):
        raise InputError(f"header value of {key!r} must be text, a number or a list")
    if isinstance(val, (float, np.floating)):
        return repr(float(val))
    if isinstance(val, (bool, np.bool_)):
        return "1" if val else "0"
    s = str(val)
    if any(c in s for c in "{}") or ("\n" in s and key != "description"):
        raise InputError(f"header value of {key!r} may not contain braces or line breaks")
    return s


def _build_header(cube: SpectralCube, dt: np.dtype, interleave: str,
                  extra_header: dict | None) -> dict[str, Any]:
    from spectral.io.envi import dtype_to_envi

    from mehs import __version__

    L, S, B = cube.shape
    h: dict[str, Any] = {
        "description": f"written by mehs {__version__}",
        "samples": S, "lines": L, "bands": B, "header offset": 0,
        "file type": "ENVI Standard", "data type": dtype_to_envi[dt.char],
        "interleave": interleave, "byte order": 0,
        "wavelength units": "Nanometers",
        "wavelength": [repr(float(w)) for w in cube.wavelengths],
    }
    if cube.fwhm is not None:
        h["fwhm"] = [repr(float(w)) for w in cube.fwhm]
    if cube.integration_time_ms is not None:
        h["tint"] = repr(float(cube.integration_time_ms))
    if cube.acquisition_date:
        h["acquisition date"] = format_acquisition_date(cube.acquisition_date)
    if cube.default_bands is not None:
        h["default bands"] = [str(b + 1) for b in cube.default_bands]
    if cube.binning is not None:
        h["binning"] = [str(int(b)) for b in cube.binning]
    h["data units"] = cube.units
    if cube.dark_subtracted:
        h["dark subtracted"] = "1"
    for k, v in (cube.metadata or {}).items():
        key = str(k).strip().lower()
        if key in MANAGED_KEYS or key.startswith("_"):
            continue
        try:
            _header_value(key, v)
        except InputError as exc:
            # metadata from other formats (e.g. EXR channel names with commas)
            # must not block writing the cube itself
            warnings.warn(f"metadata key {key!r} not written: {exc.problem}", stacklevel=4)
            continue
        h[key] = v
    for k, v in (extra_header or {}).items():
        key = str(k).strip().lower()
        if key in STRUCTURAL_KEYS:
            raise InputError(f"extra_header may not set {key!r} (it describes the data layout)")
        h[key] = v
    out = {}
    for k, v in h.items():
        if not k or "=" in k or "\n" in k or k.startswith(";"):
            raise InputError(f"invalid ENVI header key {k!r}")
        out[k] = v if k in STRUCTURAL_KEYS else _header_value(k, v)
    return out


def _check_cast(chunk: np.ndarray, dt: np.dtype) -> None:
    """Refuse casts that would wrap around or turn NaN into an integer."""
    if dt.kind not in "iu" or chunk.size == 0 or np.can_cast(chunk.dtype, dt, "safe"):
        return
    if chunk.dtype.kind == "f":
        if not np.all(np.isfinite(chunk)):
            raise InputError(f"cannot store NaN/Inf as {dt.name}")
    elif chunk.dtype.kind not in "iub":
        raise InputError(f"cannot store {chunk.dtype.name} data as {dt.name}")
    info = np.iinfo(dt)
    lo, hi = chunk.min(), chunk.max()
    if lo < info.min or hi > info.max:
        raise InputError(f"values {lo}..{hi} do not fit in {dt.name} "
                         f"({info.min}..{info.max})")


def _write_data(fh, data: np.ndarray, dt: np.dtype, interleave: str, hasher=None) -> None:
    file_dt = dt.newbyteorder("<")
    L, S, B = data.shape
    itemsize = max(dt.itemsize, data.dtype.itemsize)
    round_ = dt.kind in "iu" and data.dtype.kind == "f"
    if interleave == "bsq":
        # file order (bands, lines, samples): whole bands at a time
        step = max(1, _CHUNK_BYTES // max(1, L * S * itemsize))
        ranges = [(b, min(B, b + step)) for b in range(0, B, step)]
        take = lambda a, b: data[:, :, a:b].transpose(2, 0, 1)  # noqa: E731
    else:
        step = max(1, _CHUNK_BYTES // max(1, S * B * itemsize))
        ranges = [(i, min(L, i + step)) for i in range(0, L, step)]
        if interleave == "bil":
            take = lambda a, b: data[a:b].transpose(0, 2, 1)  # noqa: E731
        else:
            take = lambda a, b: data[a:b]  # noqa: E731
    from mehs.io.streaming import CacheDropper

    dropper = CacheDropper(fh.fileno(), L * S * B * file_dt.itemsize)
    # each chunk is hashed on a thread while it is written (hashlib releases the GIL): a
    # 512² cube's 214 MB took 0.2 s to hash and 0.1 s to write, one after the other, in
    # every `mehs fuse` (issue 16); the chunks are hashed in order, one at a time
    pool = None
    if hasher is not None and len(ranges) > 1:
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(1, thread_name_prefix="mehs-sha256")
    hashing = None
    try:
        offset = 0
        for a, b in ranges:
            chunk = np.asarray(take(a, b))
            if round_:
                # rounded first: 65535.3 stores as 65535, -0.3 as 0 ("round to nearest,
                # must fit")
                chunk = np.rint(chunk)
            _check_cast(chunk, dt)
            chunk = chunk.astype(file_dt, order="C", copy=False)
            view = memoryview(chunk).cast("B")            # the bytes as they go to the file
            if hashing is not None:
                hashing.result()
            if pool is not None:
                hashing = pool.submit(hasher.update, view)
            elif hasher is not None:
                hasher.update(view)
            chunk.tofile(fh)
            fh.flush()
            dropper.written(offset, chunk.nbytes)
            offset += chunk.nbytes
        if hashing is not None:
            hashing.result()
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    dropper.finish()


def write_envi(hdr_path: str | Path, cube: SpectralCube, *, dtype: Any = None,
               interleave: str = "bil", data_ext: str = ".raw", overwrite: bool = True,
               extra_header: dict | None = None, sha256: dict | None = None) -> Path:
    """Write ``cube`` as an ENVI header + data file, atomically; return the header path.

    The data file (``<stem><data_ext>``) is written chunk by chunk to a
    temporary name and renamed; the header is written last the same way, so
    a header's presence means the pair is complete (when overwriting, the old
    header is removed first). Byte order is always 0 (little-endian), header
    offset 0.

    Parameters
    ----------
    hdr_path
        Destination header, must end in ``.hdr``.
    cube
        The cube; ``data`` (lines, samples, bands) may be a memmap.
    dtype
        Stored data type (default: the cube's). Float → integer casts round to
        nearest and must fit the type (no NaN, no wrap-around) or
        :class:`InputError` is raised.
    interleave
        ``"bil"`` (default, Specim), ``"bip"`` or ``"bsq"``.
    data_ext
        Data-file extension: ``".raw"`` for raw cubes, ``".dat"`` for float
        results (Specim layout), or ``""``.
    overwrite
        If false, refuse (InputError) when the header or data file exists —
        used for raw captures.
    extra_header
        Additional header keys (override ``cube.metadata``; layout keys such as
        ``samples`` are refused). ``reflectance scale factor`` from a read cube is
        *not* written back (its data are already scaled); pass it here only
        with data that are scaled accordingly.
    sha256
        A dict to receive ``{file name: hex SHA-256}`` of the header and the data file,
        the data hashed as it is written (no second read of a cube the writer has just
        dropped from the page cache: 0.7 s for a 512² float32 cube).

    Writes ``wavelength``, ``fwhm``, ``wavelength units = Nanometers``,
    ``tint`` (ms), ``acquisition date`` (Specim form), ``default bands``
    (1-based), ``binning``, ``data units``, ``dark subtracted`` and the
    cube's other metadata keys.
    """
    hp = Path(hdr_path)
    if hp.suffix.lower() != ".hdr":
        raise InputError("an ENVI header path must end in .hdr", hp)
    if not isinstance(cube, SpectralCube):
        raise InputError(f"write_envi needs a SpectralCube, got {type(cube).__name__}", hp)
    inter = str(interleave).lower()
    if inter not in INTERLEAVES:
        raise InputError(f"interleave must be bil, bip or bsq, got {interleave!r}", hp)
    if data_ext and not data_ext.startswith("."):
        data_ext = "." + data_ext
    if data_ext.lower() == ".hdr":
        raise InputError("data_ext may not be .hdr", hp)
    dp = hp.with_name(hp.stem + data_ext)
    try:
        dt = _target_dtype(cube.data.dtype, dtype)
        header = _build_header(cube, dt, inter, extra_header)
    except InputError as exc:
        raise InputError(exc.problem, hp) from None
    if not overwrite:
        for p in (hp, dp):
            if p.exists():
                raise InputError("refusing to overwrite an existing file", p)
    # An ENVI header does not name its data file: another file with the header's stem and a
    # data extension would make the new pair ambiguous to every reader (mehs refuses it,
    # SPy and ENVI pick by their own order). The old header's own data file is replaced
    # with it; any other is refused before anything is written.
    from mehs.io.envi import data_file_candidates

    old_data = None
    others = [f for f in data_file_candidates(hp, inter) if not (dp.exists() and
                                                                 os.path.samefile(f, dp))]
    if others and hp.is_file() and len(others) == 1:
        old_data = others.pop()
    if others:
        raise InputError(f"{', '.join(f.name for f in others)} would also read as this "
                         f"header's data; remove it or write with its extension", hp)
    from spectral.io.envi import write_envi_header

    try:
        with atomic_path(dp, overwrite=overwrite) as tmp:
            hasher = None
            if sha256 is not None:
                import hashlib

                hasher = hashlib.sha256()
            with open(tmp, "wb") as fh:
                _write_data(fh, cube.data, dt, inter, hasher)
                fh.flush()
                os.fsync(fh.fileno())
            if hp.exists():
                hp.unlink()  # old header must not describe the new data, even briefly
            if old_data is not None:
                old_data.unlink(missing_ok=True)   # the replaced pair's data (another name)
    except InputError as exc:
        raise InputError(exc.problem, exc.path or dp) from None
    with atomic_path(hp, overwrite=overwrite) as tmp:
        write_envi_header(str(tmp), header)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
            if sha256 is not None:
                import hashlib

                sha256[hp.name] = hashlib.sha256(fh.read()).hexdigest()
    if hasher is not None:
        sha256[dp.name] = hasher.hexdigest()
    return hp
