"""The Harvard hyperspectral dataset (Chakrabarti & Zickler 2011): cube, ``lbl`` mask and
``calib.txt``.

Layout: one MATLAB v5 ``.mat`` per scene (``img1.mat``, ``imga1.mat`` …) with ``ref``
(1040×1392×31, double; 420–720 nm, 10 nm) and ``lbl`` (1040×1392); the dataset also ships
``calib.txt``, 31 per-band factors.

``lbl`` polarity (:data:`LBL_POLARITIES`, option ``harvard_lbl``)
    Default ``"zero-excluded"``: ``lbl`` marks the pixels to use, and the moving objects
    (leaves, people) that changed during the scan are 0. Those pixels are masked (bit 2,
    "ghost", of :mod:`mehs.ssr.data`'s masks) and enter no metric and no training sample.
    This is the polarity of the public loaders found (``HarvardHSIDataset`` in
    github.com/Gesetz13/Moi: ``hsi[lbl == 0] = 0``); the dataset's own readme could not be
    consulted, so the polarity is an option: ``"nonzero-excluded"`` masks the pixels where
    ``lbl`` is non-zero instead, ``"ignore"`` masks nothing. A scene whose ``lbl`` leaves no
    pixel usable is refused rather than scored empty.

``calib.txt`` (option ``harvard_calib``)
    Not applied by default (``"none"``: ``ref`` as stored, as the SSR literature's loaders
    read it). Public code disagrees on its direction: Brainard's
    ``s_ProcessHarvardHyperspectralTest.m`` (RenderToolbox / SimToolbox) *divides* ``ref``
    band by band by it, ``HarvardHSIDataset`` (Gesetz13/Moi) *multiplies*; so both are
    offered (``"divide"``, ``"multiply"``) and neither is guessed. The file is looked for
    beside the scene, then in the folders above it up to the dataset root; its 31
    numbers belong to the 31 stored bands (before any band selection).

The cube starts at 420 nm: nothing is extrapolated. The default band selection keeps its
29 bands in 400–700 nm, models' 400 and 410 nm outputs go unscored, and the
pseudo-HDR-RGB is integrated over 420–700 nm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.io.matfile import read_mat_variables

HARVARD_BANDS = np.arange(420.0, 721.0, 10.0)
#: Mask value of a pixel Harvard's ``lbl`` excludes (bit 2, "ghost": it moved during the scan).
HARVARD_MOTION = 2
#: Readings of ``lbl`` (see module notes); the first is the default.
LBL_POLARITIES = ("zero-excluded", "nonzero-excluded", "ignore")
#: Uses of ``calib.txt`` (see module notes); the first is the default.
CALIB_MODES = ("none", "divide", "multiply")
#: Folders above a scene searched for ``calib.txt`` (the scene's own first).
_CALIB_DEPTH = 3


def read_harvard(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A Harvard ``.mat`` → ``(cube (H, W, 31) as stored, bands 420:720:10, info)``.

    The ``lbl`` mask is read by :func:`harvard_mask`, ``calib.txt`` applied by
    :func:`apply_harvard_calib`, not here.
    """
    path = Path(path)
    cube = read_mat_variables(path, ("ref",))["ref"]
    if cube.dtype.kind not in "fiub":
        raise FormatError(f"'ref' must be real numbers, got {cube.dtype}", path)
    if cube.ndim != 3 or cube.shape[2] != HARVARD_BANDS.size:
        raise FormatError(f"'ref' must be rows × columns × 31 bands (420–720 nm), got shape "
                          f"{cube.shape}", path)
    return cube, HARVARD_BANDS.copy(), {"variable": "ref", "bands_from": "Harvard 420:720:10"}


def find_calib(scene: Path) -> Path | None:
    """``calib.txt`` beside ``scene`` or in one of the folders above it, else ``None``."""
    d = Path(scene).resolve().parent
    for _ in range(_CALIB_DEPTH):
        f = d / "calib.txt"
        if f.is_file():
            return f
        if d.parent == d:
            break
        d = d.parent
    return None


def read_calib(path: str | Path) -> np.ndarray:
    """The 31 per-band factors of a Harvard ``calib.txt`` (whitespace- or comma-separated),
    float64; :class:`FormatError` naming the file for anything else."""
    path = Path(path)
    text = path.read_text(encoding="utf-8", errors="replace").replace(",", " ")
    try:
        f = np.asarray([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise FormatError("calib.txt must hold numbers only", path) from None
    if f.size != HARVARD_BANDS.size:
        raise FormatError(f"calib.txt holds {f.size} numbers; the Harvard cube has "
                          f"{HARVARD_BANDS.size} bands (420–720 nm)", path)
    if not np.all(np.isfinite(f) & (f > 0)):
        raise FormatError("calib.txt factors must be finite and > 0", path)
    return f


def apply_harvard_calib(cube: np.ndarray, scene: Path, mode: str) -> tuple[np.ndarray, dict]:
    """``cube`` (H, W, 31) with ``calib.txt`` applied per band (``mode`` of
    :data:`CALIB_MODES`), and what was done for the record."""
    if mode not in CALIB_MODES:
        raise InputError(f"harvard_calib must be one of {', '.join(CALIB_MODES)}, got {mode!r}")
    if mode == "none":
        return cube, {"calib": "not applied"}
    f = find_calib(scene)
    if f is None:
        raise InputError(f"harvard_calib={mode!r} needs the dataset's calib.txt beside the "
                         "scene or in a folder above it; none found", scene)
    k = read_calib(f)
    out = cube / k if mode == "divide" else cube * k
    return out, {"calib": mode, "calib_file": str(f)}


def harvard_mask(path: Path, polarity: str = LBL_POLARITIES[0]) -> np.ndarray | None:
    """Harvard's ``lbl`` as a mask ``(H, W)`` uint8, :data:`HARVARD_MOTION` on the pixels
    ``polarity`` excludes; ``None`` for a file without ``lbl`` or ``polarity="ignore"``."""
    if polarity not in LBL_POLARITIES:
        raise InputError(f"harvard_lbl must be one of {', '.join(LBL_POLARITIES)}, "
                         f"got {polarity!r}")
    if polarity == "ignore":
        return None
    try:
        lbl = read_mat_variables(path, ("lbl",))["lbl"]
    except FormatError as exc:
        if "no variable 'lbl'" in exc.problem:
            return None
        raise
    if lbl.ndim != 2 or lbl.dtype.kind not in "fiub":
        raise FormatError(f"'lbl' must be a rows × columns mask, got {lbl.dtype} "
                          f"{lbl.shape}", path)
    excluded = (lbl == 0) if polarity == "zero-excluded" else (lbl != 0)
    if excluded.all():
        which = "0" if polarity == "zero-excluded" else "non-zero"
        raise FormatError(f"'lbl' marks no pixel as usable ({which} everywhere, read with "
                          f"harvard_lbl={polarity!r}): nothing of this scene could be scored",
                          path)
    return np.where(excluded, HARVARD_MOTION, 0).astype(np.uint8)
