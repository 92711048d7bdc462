"""File formats: ENVI cubes, Specim IQ capture folders, OpenEXR images; atomic writes.

``import mehs.io`` stays light: SPy, OpenCV and OpenEXR are imported only
when a function needs them.
"""

from __future__ import annotations

from pathlib import Path

from mehs.errors import FormatError, InputError
from mehs.io.envi import read_envi, read_envi_header, write_envi
from mehs.io.specim import (SpecimCapture, find_captures, is_specim_folder,
                            read_specim_folder, write_specim_folder)

__all__ = ["load_cube", "read_envi", "read_envi_header", "write_envi", "SpecimCapture",
           "read_specim_folder", "write_specim_folder", "find_captures", "is_specim_folder"]


def load_cube(path: str | Path, *, memmap: bool = True):
    """Open a spectral cube from an ENVI file, a Specim IQ folder or a spectral EXR.

    Parameters
    ----------
    path
        An ENVI header or data file; a Specim IQ capture folder (its raw cube
        is returned; the dark reference is not required); a folder holding only
        one IQ result ``REFLECTANCE_<id>.hdr`` (itself or in ``results/``; that
        cube is returned); or a ``.exr`` with one channel per wavelength.

    Returns
    -------
    SpectralCube
        ``(lines, samples, bands)``.

    Raises
    ------
    InputError
        ``path`` does not exist, or is a folder that is not a Specim IQ capture.
    FormatError
        The file does not follow its format.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("file or folder does not exist", p)
    if p.is_dir():
        if is_specim_folder(p):
            return read_specim_folder(p, require_dark=False, memmap=memmap).raw
        # Published IQ data sets often ship only the camera's result: a folder
        # holding REFLECTANCE_<id>.hdr/.dat and <id>.png, no capture/ (e.g. the
        # fire-blight set, DOI 10.57745/R6AMN3, "plant <N>" folders).
        results = sorted({*p.glob("REFLECTANCE_*.hdr"), *p.glob("results/REFLECTANCE_*.hdr")})
        if len(results) == 1:
            cube = read_envi(results[0], memmap=memmap)
            if cube.units in ("unknown", "DN"):
                cube.units = "reflectance"
            return cube
        hint = " (a mehs scene folder? use mehs.synthesis.bracket.load_bracket)" \
            if (p / "scene.json").is_file() else ""
        raise InputError("folder is not a Specim IQ capture (no manifest.xml or "
                         f"capture/<id>.hdr){hint}", p)
    if p.suffix.lower() == ".exr":
        from mehs.io.exr import read_exr_spectral

        return read_exr_spectral(p)
    try:
        return read_envi(p, memmap=memmap)
    except FormatError as exc:
        if p.suffix.lower() != ".hdr" and "no ENVI header found" in exc.problem:
            raise FormatError("not a recognised cube (expected an ENVI .hdr/data file, "
                              "a Specim IQ folder or a spectral .exr)", p) from None
        raise
