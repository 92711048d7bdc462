"""Exports of HDR-HS cubes for spectral rendering / image-based lighting (paper §3.5).

Two layouts, both 32-bit float OpenEXR, unnormalised radiance:

Per-wavelength sequence (:func:`export_per_wavelength`)
    ``<out>/<prefix>_000.exr … <prefix>_<N-1>.exr``: one single-channel
    (``Y``) image per band in ascending wavelength order, numbered from 0 and
    zero-padded to 3 digits (printf pattern ``<prefix>_%03d.exr``, the
    numbered-sequence form renderers and image tools load as a stack; 31 files
    for 400–700 nm). Each file also carries its band in the header
    (``wavelength`` in nm, ``bandIndex``, ``wavelengths`` of the whole set).
    ``<out>/<prefix>_wavelengths.txt`` lists one line per file:
    ``<index> <wavelength_nm> <file name>`` after a ``#`` header line, and
    ``<out>/<prefix>_wavelengths.json`` holds the same as JSON together with
    the units and FWHMs. Rows are the cube's lines and columns its samples (native
    ENVI orientation, as in every mehs image; a renderer's lat-long map has the zenith
    in row 0). The set is written all-or-nothing (:func:`export_per_wavelength`).

Single spectral file (:func:`export_spectral_exr`)
    One multi-channel EXR in the Fichet et al. 2021 layout
    (:func:`mehs.io.exr.write_exr_spectral`: channels ``S0.<λ>nm``,
    wavelengths in the header).

References
----------
- Fichet, A., Pacanowski, R., & Wilkie, A. (2021). An OpenEXR Layout for
  Spectral Images. JCGT 10(3).
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

import numpy as np

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.io.atomic import atomic_path, write_json_atomic, write_text_atomic
from mehs.io.exr import write_exr_gray, write_exr_spectral

_PREFIX_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def _check_cube(cube, *, half: bool = False) -> SpectralCube:
    if not isinstance(cube, SpectralCube):
        raise InputError(f"expected a SpectralCube, got {type(cube).__name__}")
    # checked before the first file is written: the EXR writer refuses NaN (and
    # values beyond half range) only band by band, which left the earlier bands'
    # files behind as a partial export
    from mehs.io.exr import FLOAT32_MAX, HALF_MAX

    data = cube.data
    step = max(1, (1 << 24) // max(1, data[0].size))
    peak = 0.0
    for i in range(0, data.shape[0], step):
        block = np.asarray(data[i:i + step])
        if np.issubdtype(block.dtype, np.floating) and not np.isfinite(block).all():
            bad = int(np.count_nonzero(~np.isfinite(np.asarray(data, dtype=np.float32))))
            raise InputError(f"the cube holds {bad} NaN/Inf values; an EXR export would "
                             "carry them into the renderer", cube.source)
        if block.size:
            peak = max(peak, float(np.abs(block).max()))
    if half and peak > HALF_MAX:
        raise InputError(f"value {peak:.6g} exceeds the half-float range (±{HALF_MAX:g}); "
                         "export 32-bit float (no --half) or rescale", cube.source)
    if peak > FLOAT32_MAX:
        raise InputError(f"value {peak:.6g} exceeds the 32-bit float range "
                         f"(±{FLOAT32_MAX:.6g}) of an EXR; rescale", cube.source)
    return cube


def valid_prefix(prefix: str) -> str:
    """Return ``prefix`` if it is a plain file-name stem (letters, digits, ``_.-``), else raise."""
    if not _PREFIX_RE.match(str(prefix)):
        raise InputError(f"prefix {prefix!r} must be letters, digits, '_', '.', '-'")
    return str(prefix)


def export_per_wavelength(cube: SpectralCube, out_dir: str | Path, *, prefix: str = "band",
                          half: bool = False) -> list[Path]:
    """Write one grayscale EXR per band plus the wavelength list files, as one set.

    Parameters
    ----------
    cube
        ``(lines, samples, bands)`` cube; lines become image rows.
    out_dir
        Folder to write into (created if needed). ``<prefix>_<digits>.exr`` files of
        an earlier export there that this one does not write are removed once it is
        written; such a file that ``mehs export`` did not write (no ``bandIndex`` /
        ``wavelength`` header), or one of this export's names, is refused before anything
        is written.
    prefix
        File-name prefix (letters, digits, ``_.-``).
    half
        Store half floats (default 32-bit float).

    Returns
    -------
    list[Path]
        The ``bands`` EXR paths in wavelength order.

    Notes
    -----
    All-or-nothing: every band is first written to a hidden temporary file; only when
    all are written are the earlier listing files removed, the bands renamed into
    place and the listings written, the JSON listing last. An exception while writing
    (a full disk, a failing band) leaves the folder as it was — an earlier export there
    stays whole — instead of a partial sequence, or new bands mixed with an earlier
    export's bands under that export's complete-looking listing.
    """
    cube = _check_cube(cube, half=half)
    valid_prefix(prefix)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", out)
    out.mkdir(parents=True, exist_ok=True)
    wl = cube.wavelengths
    width = max(3, len(str(wl.size - 1)))
    names = [f"{prefix}_{i:0{width}d}.exr" for i in range(wl.size)]
    stale = _stale_bands(out, prefix, names)   # refuses foreign files before any write
    all_wl = [float(w) for w in wl]
    listings = [out / f"{prefix}_wavelengths.txt", out / f"{prefix}_wavelengths.json"]
    paths = [out / n for n in names]
    with contextlib.ExitStack() as staged:
        for i, path in enumerate(paths):
            tmp = staged.enter_context(atomic_path(path))   # renamed onto path on exit
            plane = np.asarray(cube.data[:, :, i], dtype=np.float32)
            # errors and warnings name the band, not its hidden temporary file
            write_exr_gray(tmp, plane, half=half, name=path, header={
                "wavelength": float(wl[i]), "bandIndex": int(i), "wavelengths": all_wl,
                "mehsUnits": str(cube.units), **_scale_header(cube)})
        # every band is written: the earlier listing goes first, so that an interruption
        # while the bands are renamed leaves no listing that vouches for a mixed set
        for f in listings:
            f.unlink(missing_ok=True)
    for f in stale:
        f.unlink(missing_ok=True)
    lines = ["# index wavelength_nm file"] + [f"{i} {repr(float(w))} {n}"
                                              for i, (w, n) in enumerate(zip(wl, names))]
    write_text_atomic(listings[0], "\n".join(lines) + "\n")
    write_json_atomic(listings[1], {
        "format": "mehs-per-wavelength-exr/1",
        "pattern": f"{prefix}_%0{width}d.exr",
        "units": str(cube.units),
        "radiance_scale": radiance_scale(cube),
        "wavelengths_nm": all_wl,
        "fwhm_nm": None if cube.fwhm is None else [float(f) for f in cube.fwhm],
        "files": names,
    })
    return paths


def _band_pattern(prefix: str) -> re.Pattern:
    return re.compile(rf"{re.escape(prefix)}_\d+\.exr")


def _is_exported_band(path: Path) -> bool:
    """Whether ``path`` is a band file a per-wavelength export wrote (its header has the
    ``bandIndex`` and ``wavelength`` attributes that :func:`export_per_wavelength` sets)."""
    import OpenEXR

    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except Exception:   # not an EXR, or a damaged one: not ours either way
        return False
    return "bandIndex" in header and "wavelength" in header


def _stale_bands(out: Path, prefix: str, names: list[str]) -> list[Path]:
    """Band files of an earlier export in ``out`` that an export writing ``names`` leaves
    behind (to be removed once it is written).

    An earlier export of more bands (or another padding) would leave files a glob or
    ``%03d`` loader takes for this export's, at other wavelengths; removing them is only
    right for files an export wrote, so a matching file of another origin
    (``band_2024.exr`` from elsewhere) is refused here, before any write, naming it — as
    is one this export would replace (``band_000.exr`` from elsewhere).
    """
    keep = set(names)
    pat = _band_pattern(prefix)
    found = sorted(f for f in out.iterdir() if pat.fullmatch(f.name) and f.is_file())
    stale = [f for f in found if f.name not in keep]
    # one this export would replace is checked too: it is no earlier export's (whose
    # listing the CLI's overwrite check finds) unless an export wrote it (a killed run's)
    foreign = [f for f in found if not _is_exported_band(f)]
    if foreign:
        more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
        raise InputError(f"a file named like a band of this export{more} was not written by "
                         f"mehs export; loaders of the {prefix}_NNN.exr sequence would take it "
                         "for a band — move it, or choose another --prefix or folder",
                         foreign[0])
    return stale


def remove_per_wavelength_export(out_dir: str | Path, prefix: str = "band") -> list[Path]:
    """Remove an earlier per-wavelength export of ``prefix`` from ``out_dir``: its listing
    files and the ``<prefix>_<digits>.exr`` bands an export wrote (other files are kept).

    Returns
    -------
    list[Path]
        The removed files.
    """
    out = Path(out_dir)
    if not out.is_dir():
        return []
    pat = _band_pattern(valid_prefix(prefix))
    gone = [out / f"{prefix}_wavelengths.json", out / f"{prefix}_wavelengths.txt"]
    gone = [f for f in gone if f.is_file()]
    gone += sorted(f for f in out.iterdir()
                   if pat.fullmatch(f.name) and f.is_file() and _is_exported_band(f))
    for f in gone:      # the JSON listing first: no listing outlives the set it lists
        f.unlink(missing_ok=True)
    return gone


def export_spectral_exr(cube: SpectralCube, path: str | Path, *, half: bool = False,
                        name: str | Path | None = None) -> Path:
    """Write the cube as one multi-channel spectral EXR (Fichet 2021 layout); ``name``: the
    file errors and warnings name when ``path`` is a temporary one."""
    return write_exr_spectral(path, _check_cube(cube, half=half), half=half,
                              header=_scale_header(cube), name=name)


def radiance_scale(cube: SpectralCube) -> float | None:
    """The power-of-two factor a dataset cube's values carry (``mehs radiance scale`` in its
    header: stored = radiance × scale, to fit half floats), or None."""
    return parse_radiance_scale((cube.metadata or {}).get("mehs radiance scale"), cube.source)


def parse_radiance_scale(value, where=None) -> float | None:
    """A stored radiance scale (a number, or its text from a header or listing), validated:
    finite and > 0; None when absent. :class:`FormatError` naming ``where`` otherwise."""
    if value is None or value == "":
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise FormatError(f"the radiance scale ('mehs radiance scale') must be a number, "
                          f"got {value!r}", where) from None
    if not (np.isfinite(f) and f > 0):
        raise FormatError(f"the radiance scale ('mehs radiance scale') must be finite and > 0, "
                          f"got {value!r}", where)
    return f


def _scale_header(cube: SpectralCube) -> dict[str, float]:
    # without it the exported values are off by the dataset's 2^-k with nothing to say so
    f = radiance_scale(cube)
    return {} if f is None else {"mehsRadianceScale": f}
