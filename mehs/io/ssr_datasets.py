"""Readers for the public spectral super-resolution (SSR) datasets.

=========  ==========================================================  ======================
format     layout                                                      bands
=========  ==========================================================  ======================
``arad1k`` NTIRE 2022 ARAD-1K: ``*.mat`` (MATLAB v7.3 = HDF5) with       ``bands`` (31, 400–700)
           ``cube`` (482×512×31 in MATLAB, stored ``(31, W, H)``),
           ``bands``, ``norm_factor``; RGB ``<stem>.jpg``; split lists
           ``train_list.txt`` / ``valid_list.txt`` (or Train_/Valid_ folders)
``arad``   ARAD / BGU-HS, NTIRE 2018–2020: ``*.mat`` with ``rad`` and   ``bands``
           ``bands`` (v7.3 or v5); RGB ``<stem>_clean.png`` / ``.jpg``
``icvl``   ICVL (Arad & Ben-Shahar 2016): ``*.mat`` v7.3, ``rad``,      ``bands``
           ``bands``
``cave``   CAVE (Yasuma et al. 2010): one folder per scene of 31        400–700 nm, 10 nm
           16-bit PNGs ``<name>_ms_01.png`` … ``_31.png``; RGB
           ``<name>_RGB.bmp``
``kaust``  KAUST-HS (Li et al. 2021): ``*.h5`` / ``*.hdf5`` with one     ``bands`` /
           3-D dataset (``img``, ``cube``, ``rad``, ``data`` or the      ``wavelengths`` if
           only one)                                                   stored, else 400–730
``harvard`` Harvard (Chakrabarti & Zickler 2011): one MATLAB v5 ``.mat``  420–720 nm, 10 nm
           per scene (``img1.mat``, ``imga1.mat`` …) with ``ref``
           (1040×1392×31, double) and ``lbl`` (1040×1392), no RGB
``kaist``  KAIST (Choi et al. 2017): ``sceneNN_reflectance.exr`` with    ``w<λ>nm`` names:
           channels ``w420nm`` … ``w720nm`` (and ``R, G, B``, unused)   420–720 nm, 10 nm
``cassi28`` the CASSI benchmarks' KAIST cubes: ``.mat`` with ``img``    453.5 … 648 nm (28)
           (256×256×28) or ``HSI`` (2704×3376×28)
=========  ==========================================================  ======================

KAIST and its CASSI derivatives: :mod:`mehs.io.ssr_kaist` (layouts and their sources).

Harvard: :mod:`mehs.io.ssr_harvard` (``lbl`` polarity, ``calib.txt``, bands). Its moving
objects are masked (bit 2, "ghost", of :mod:`mehs.ssr.data`'s masks; :func:`read_source_mask`).

MATLAB files are read by :mod:`mehs.io.matfile`: :mod:`h5py` (v7.3: HDF5 behind a 512-byte
MATLAB userblock; arrays are stored column-major, so every axis order is reversed: a MATLAB
``H×W×B`` cube reads as ``(B, W, H)`` and is transposed back) or :func:`scipy.io.loadmat`
(v5). No hand-written parser.

Every cube becomes float32 ``(H, W, B)`` (``H`` = MATLAB rows) and goes through the explicit,
recorded options of :class:`SourceOptions`: band selection (default: the bands in 400–700 nm),
central crop, scale (default 1: values as stored, relative units). The HDR-RGB input is the
pseudo-HDR-RGB of the cube (:func:`mehs.rgb.spectra_to_linear_sRGB`, rounded to half float like
``mehs build``'s EXR); the LDR input is the dataset's own RGB image when it ships one (ARAD JPG,
CAVE BMP), else :func:`mehs.rgb.ldr_rgb` of the HDR-RGB.

References
----------
- Arad et al. (2022), "NTIRE 2022 spectral recovery challenge and data set", CVPRW.
- Arad & Ben-Shahar (2016), "Sparse recovery of hyperspectral signal from natural RGB
  images", ECCV (ICVL / BGU-HS).
- Yasuma, Mitsunaga, Iso & Nayar (2010), "Generalized assorted pixel camera", IEEE TIP (CAVE).
- Li, Fu, Heidrich et al. (2021), "Multispectral illumination estimation using deep
  unrolling network", ICCV (KAUST-HS).
- Chakrabarti & Zickler (2011), "Statistics of real-world hyperspectral images", CVPR
  (Harvard).
- MathWorks, "MAT-file versions" (v7.3 is HDF5 with a 512-byte header).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import FormatError, InputError
# read_mat_variables lived here first; ssr_kaist and outside code still import it from here
from mehs.io.matfile import read_mat_variables
from mehs.io.ssr_harvard import HARVARD_MOTION  # noqa: F401 (re-exported)
from mehs.io.ssr_harvard import (CALIB_MODES, LBL_POLARITIES, apply_harvard_calib, harvard_mask,
                                 read_harvard)
from mehs.io.ssr_kaist import read_cassi28, read_kaist

#: Public dataset formats read here.
FORMATS = ("arad1k", "arad", "icvl", "cave", "kaust", "harvard", "kaist", "cassi28")

_CAVE_BANDS = np.arange(400.0, 701.0, 10.0)
_KAUST_DEFAULT = np.arange(400.0, 731.0, 10.0)
_KAUST_KEYS = ("img", "cube", "rad", "data", "hsi", "reflectance")
_RGB_EXT = (".jpg", ".jpeg", ".png", ".bmp")
RGB_ENCODINGS = ("auto", "linear", "srgb")
#: Words of list-file stems and folder names that name a split. Folder names are the
#: challenges' own: ``Train_Spec``/``Valid_Spec`` (NTIRE 2022), ``NTIRE2020_Train_Spectral``/
#: ``NTIRE2020_Validation_Spectral`` (NTIRE 2020, the paper's ARAD HS),
#: ``NTIRE2018_Train1_Spectral``/``NTIRE2018_Validate_Spectral`` (NTIRE 2018).
_SPLIT_WORDS = {"train": "train", "training": "train", "valid": "val", "val": "val",
                "validation": "val", "validate": "val", "test": "test", "testing": "test"}


@dataclass(frozen=True)
class SourceOptions:
    """Explicit reading options, recorded with every result.

    Attributes
    ----------
    bands
        ``"visible"`` (bands within 400–700 nm, default), ``"all"``, or band centres (nm)
        to keep (each must exist within 0.5 nm).
    crop
        ``(height, width)`` of a central crop, or ``None``.
    scale
        Multiplies the stored values (1 = as stored).
    harvard_lbl
        Harvard's ``lbl``: ``"zero-excluded"`` (default: 0 marks moving objects),
        ``"nonzero-excluded"`` or ``"ignore"`` (:mod:`mehs.io.ssr_harvard`).
    harvard_calib
        Harvard's ``calib.txt``: ``"none"`` (default: ``ref`` as stored), ``"divide"`` or
        ``"multiply"`` per band (:mod:`mehs.io.ssr_harvard`).
    rgb_encoding
        How the dataset's own 8-bit RGB images encode light: ``"linear"`` (values
        proportional to the camera's signal), ``"srgb"`` (the sRGB transfer curve), or
        ``"auto"`` (default): linear for ARAD-1K and ARAD/BGU-HS, whose RGB images
        the NTIRE 2020/2022 challenge code made by projecting the cube through a
        camera response and scaling to 8 bits without a tone curve
        (``SpectralUtils.imTo8bit``, ``NTIRE2022Util.save_jpg``); sRGB for the others
        (CAVE's ``*_RGB.bmp`` are display renderings).
    """

    bands: Any = "visible"
    crop: tuple[int, int] | None = None
    scale: float = 1.0
    rgb_encoding: str = "auto"
    harvard_lbl: str = LBL_POLARITIES[0]
    harvard_calib: str = CALIB_MODES[0]

    def __post_init__(self) -> None:
        for name, value, allowed in (("rgb_encoding", self.rgb_encoding, RGB_ENCODINGS),
                                     ("harvard_lbl", self.harvard_lbl, LBL_POLARITIES),
                                     ("harvard_calib", self.harvard_calib, CALIB_MODES)):
            if value not in allowed:
                raise InputError(f"{name} must be one of {', '.join(allowed)}, got {value!r}")

    def rgb_encoding_for(self, fmt: str) -> str:
        """The encoding of ``fmt``'s RGB images: the option, or the format's own for auto."""
        if self.rgb_encoding != "auto":
            return self.rgb_encoding
        return "linear" if fmt in ("arad1k", "arad") else "srgb"

    def record(self, fmt: str | None = None) -> dict:
        """The options as recorded with results; the Harvard-only ones for ``fmt`` harvard
        (or when set), so other formats' records stay as they were."""
        d = asdict(self)
        if isinstance(self.bands, np.ndarray):
            d["bands"] = self.bands.tolist()
        if fmt != "harvard":
            for k, default in (("harvard_lbl", LBL_POLARITIES[0]),
                               ("harvard_calib", CALIB_MODES[0])):
                if d[k] == default:
                    del d[k]
        return d


# --------------------------------------------------------------------------- MATLAB
def _mat_cube(path: Path, cube_key: str) -> tuple[np.ndarray, np.ndarray, dict]:
    v = read_mat_variables(path, (cube_key, "bands"))
    cube = v[cube_key]
    try:
        bands = np.asarray(v["bands"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise FormatError(f"'bands' must be numbers (nm), got {v['bands'].dtype}", path) from None
    # MATLAB v7.3 stores a complex array as a compound of (real, imag); v5 as complex
    if cube.dtype.kind not in "fiub":
        raise FormatError(f"{cube_key!r} must be real numbers, got {cube.dtype}", path)
    if cube.ndim != 3:
        raise FormatError(f"{cube_key!r} must be 3-D (rows × columns × bands), got shape "
                          f"{cube.shape}", path)
    if cube.shape[2] != bands.size:
        raise FormatError(f"{cube_key!r} has {cube.shape[2]} bands but 'bands' lists "
                          f"{bands.size}", path)
    info: dict[str, Any] = {"variable": cube_key}
    if cube_key == "cube":
        try:
            nf = read_mat_variables(path, ("norm_factor",))["norm_factor"]
        except FormatError:
            nf = None  # optional in ARAD-1K
        if nf is not None:
            try:
                info["norm_factor"] = float(np.asarray(nf, dtype=np.float64).reshape(-1)[0])
            except (TypeError, ValueError, IndexError):
                raise FormatError(f"'norm_factor' must be a number, got {np.asarray(nf).dtype} "
                                  f"{np.asarray(nf).shape}", path) from None
    return cube, bands, info


# --------------------------------------------------------------------------- CAVE, KAUST
_CAVE_PNG = re.compile(r"^(.*?)_?(\d{2})\.png$", re.IGNORECASE)


def _cave_pngs(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("*.png") if _CAVE_PNG.match(p.name))


def read_cave(folder: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A CAVE scene folder of 31 PNGs → ``(cube (H, W, 31) in [0, 1], bands, info)``."""
    import cv2

    folder = Path(folder)
    pngs = _cave_pngs(folder)
    nums = sorted(int(_CAVE_PNG.match(p.name).group(2)) for p in pngs)
    if nums != list(range(1, 32)):
        missing = sorted(set(range(1, 32)) - set(nums))
        raise FormatError(f"a CAVE scene needs 31 band PNGs _01 … _31; missing "
                          f"{', '.join(f'_{m:02d}' for m in missing) or 'none'}"
                          f"{'' if len(nums) <= 31 else f' ({len(nums)} found)'}", folder)
    planes, depth = [], None
    for p in sorted(pngs, key=lambda q: int(_CAVE_PNG.match(q.name).group(2))):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FormatError("not a readable PNG (truncated?)", p)
        if img.ndim == 3:  # a few CAVE PNGs are stored with identical colour channels
            if img.shape[2] not in (3, 4) or np.any(img[..., 1:3] != img[..., :1]):
                # a colour picture (an RGB render, a mislabelled file) is no band image:
                # one channel of it would be scored as the band without a word
                raise FormatError(f"band PNG has {img.shape[2]} colour channels that differ; "
                                  "a CAVE band is one grey plane", p)
            img = img[..., 0]
        if depth is None:
            depth = img.dtype
        if img.dtype not in (np.uint8, np.uint16):
            raise FormatError(f"band PNGs must be 8- or 16-bit, got {img.dtype}", p)
        if img.dtype != depth:
            raise FormatError(f"band PNG is {img.dtype}, the first band {depth}: a scene's "
                              "bands must share one bit depth", p)
        if planes and img.shape != planes[0].shape:
            raise FormatError(f"band is {img.shape}, the first band {planes[0].shape}", p)
        planes.append(img)
    full = 65535.0 if depth == np.uint16 else 255.0
    cube = np.stack(planes, axis=-1).astype(np.float32) / np.float32(full)
    return cube, _CAVE_BANDS.copy(), {"bit_depth": 16 if full > 255 else 8, "divided_by": full}


def read_kaust(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A KAUST-HS ``.h5`` file → ``(cube (H, W, B), bands, info)`` (see module notes)."""
    import h5py

    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            sets = {k: f[k] for k in f.keys() if isinstance(f[k], h5py.Dataset)}
            name = next((k for k in _KAUST_KEYS if k in sets and sets[k].ndim == 3), None)
            three = [k for k, d in sets.items() if d.ndim == 3]
            if name is None and len(three) == 1:
                name = three[0]
            if name is None:
                raise FormatError(f"no 3-D image dataset (looked for {', '.join(_KAUST_KEYS)}; "
                                  f"datasets: {', '.join(sorted(sets)) or 'none'})", path)
            ds = sets[name]
            data = np.asarray(ds[()])
            matlab = "MATLAB_class" in ds.attrs or f.userblock_size >= 128
            bkey = next((k for k in ("bands", "wavelengths", "wavelength") if k in sets), None)
            bands = None if bkey is None else np.asarray(sets[bkey][()], np.float64).reshape(-1)
            if bands is None:
                attr = next((ds.attrs[k] for k in ("bands", "wavelengths") if k in ds.attrs), None)
                bands = None if attr is None else np.asarray(attr, np.float64).reshape(-1)
    except FormatError:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise FormatError(f"unreadable or truncated HDF5 file ({exc})", path) from None
    if matlab:
        data = data.transpose()
    n_b = bands.size if bands is not None else _KAUST_DEFAULT.size
    axes = [i for i, s in enumerate(data.shape) if s == n_b]
    if not axes:
        raise FormatError(f"dataset {name!r} has shape {data.shape}: no axis of {n_b} bands"
                          + ("" if bands is not None else " (no 'bands' stored; KAUST-HS has 34, "
                             "400–730 nm)"), path)
    if len(axes) > 1:
        # bands are stored first or last (B, H, W / H, W, B); a side of the image as long
        # as the band list leaves the choice to a guess, which read the cube sideways
        ends = [a for a in axes if a in (0, data.ndim - 1)]
        if len(ends) != 1:
            raise FormatError(f"dataset {name!r} has shape {data.shape}: more than one axis "
                              f"could hold the {n_b} bands; crop or store it as (H, W, B)",
                              path)
        axes = ends
    data = np.moveaxis(data, axes[-1], -1)
    info = {"dataset": name, "matlab_order": bool(matlab),
            "bands_from": bkey or ("attribute" if bands is not None else "KAUST default 400:730:10")}
    return data, (bands if bands is not None else _KAUST_DEFAULT.copy()), info


# --------------------------------------------------------------------------- Harvard
def _harvard_mask(path: Path, opts: SourceOptions) -> np.ndarray | None:
    return harvard_mask(path, opts.harvard_lbl)


#: format → reader of a scene's mask (0 = valid), for formats that ship one.
MASK_READERS = {"harvard": _harvard_mask}


def read_source_mask(fmt: str, path: str | Path, shape: tuple[int, int],
                     opts: SourceOptions = SourceOptions()) -> np.ndarray:
    """The scene's mask, uint8 ``(H, W)`` (0 = valid; :mod:`mehs.ssr.data`'s bits), after the
    same central crop as its cube (:func:`apply_options`); zeros for formats without one.

    ``shape`` is the cube's ``(H, W)`` after the options; a mask of another size is refused.
    """
    path = Path(path)
    reader = MASK_READERS.get(fmt)
    m = None if reader is None else reader(path, opts)
    if m is None:
        return np.zeros(tuple(shape), dtype=np.uint8)
    if opts.crop is not None and m.shape != tuple(shape):
        m = m[central_crop(m.shape, opts.crop, path)]
    if m.shape != tuple(shape):
        raise FormatError(f"the mask is {m.shape[0]}×{m.shape[1]}, the cube "
                          f"{shape[0]}×{shape[1]}", path)
    return np.ascontiguousarray(m)


# --------------------------------------------------------------------------- options
def central_crop(hw: tuple[int, int], crop, path: Path) -> tuple[slice, slice]:
    """The row and column slices of a central ``crop`` (H, W) of an ``hw`` image (cube,
    mask), or :class:`InputError` naming ``path`` when it does not fit."""
    h, w = (int(v) for v in hw[:2])
    ch, cw = (int(v) for v in crop)
    if not (0 < ch <= h and 0 < cw <= w):
        raise InputError(f"crop {ch}×{cw} does not fit the {h}×{w} image", path)
    return slice((h - ch) // 2, (h - ch) // 2 + ch), slice((w - cw) // 2, (w - cw) // 2 + cw)


def apply_options(cube: np.ndarray, bands: np.ndarray, opts: SourceOptions,
                  path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Band selection, central crop and scale; float32 ``(H, W, B')`` and ``(B',)``."""
    if isinstance(opts.bands, str):
        if opts.bands == "visible":
            keep = np.flatnonzero((bands >= 399.5) & (bands <= 700.5))
        elif opts.bands == "all":
            keep = np.arange(bands.size)
        else:
            raise InputError(f"bands must be 'visible', 'all' or a list of nm, got {opts.bands!r}")
    else:
        want = np.asarray(opts.bands, np.float64).reshape(-1)
        d = np.abs(bands[None, :] - want[:, None])
        if want.size == 0 or np.any(d.min(axis=1) > 0.5):
            missing = want[d.min(axis=1) > 0.5] if want.size else want
            raise InputError(f"bands {missing.tolist()} nm are not in the file (it has "
                             f"{bands.min():g}–{bands.max():g} nm, {bands.size} bands)", path)
        keep = d.argmin(axis=1)
    if keep.size == 0:
        raise InputError(f"no band in 400–700 nm (the file has {bands.min():g}–{bands.max():g} nm)",
                         path)
    if not np.all(np.isfinite(bands[keep])):
        raise FormatError("the band list holds NaN or inf", path)
    # files that list their bands from red to blue: ascending order, the data with them
    keep = keep[np.argsort(bands[keep], kind="stable")]
    if np.any(np.diff(bands[keep]) == 0):
        raise FormatError(f"the band list repeats {bands[keep][np.diff(bands[keep]) == 0][0]:g} nm",
                          path)
    rows, cols = (slice(None), slice(None)) if opts.crop is None else \
        central_crop(cube.shape[:2], opts.crop, path)
    out = np.asarray(cube[rows, cols][..., keep], dtype=np.float32)
    if opts.scale != 1.0:
        out = out * np.float32(opts.scale)
    if not np.all(np.isfinite(out)):
        raise InputError("the cube contains NaN or inf", path)
    return np.ascontiguousarray(out), bands[keep].astype(np.float64)


def read_source_cube(fmt: str, path: str | Path, opts: SourceOptions = SourceOptions()):
    """Read one scene of a public dataset: ``(cube float32 (H, W, B), bands (B,), info)``."""
    path = Path(path)
    if fmt not in READERS:
        raise InputError(f"unknown dataset format {fmt!r}; use one of {', '.join(FORMATS)}")
    cube, bands, info = READERS[fmt](path)
    if fmt == "harvard":  # per stored band, before any band selection
        cube, done = apply_harvard_calib(cube, path, opts.harvard_calib)
        info.update(done)
    data, wl = apply_options(cube, bands, opts, path)
    info.update({"format": fmt, "stored_shape": list(cube.shape), "options": opts.record(fmt)})
    return data, wl, info


#: Dispatcher: format → reader of one scene (path → raw cube (H, W, B), bands, info).
READERS = {
    "arad1k": lambda p: _mat_cube(p, "cube"),
    "arad": lambda p: _mat_cube(p, "rad"),
    "icvl": lambda p: _mat_cube(p, "rad"),
    "cave": read_cave,
    "kaust": read_kaust,
    "harvard": read_harvard,
    "kaist": read_kaist,
    "cassi28": read_cassi28,
}
