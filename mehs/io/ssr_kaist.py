"""The KAIST hyperspectral dataset (Choi et al. 2017) and its 28-band CASSI derivatives.

=========  ==========================================================  ======================
format     layout                                                      bands
=========  ==========================================================  ======================
``kaist``  KAIST (Choi, Jeon, Nam, Gutierrez & Kim 2017): one OpenEXR   from the channel
           per scene, ``sceneNN_reflectance.exr`` (2704 rows × 3376     names: 420–720 nm,
           columns), channels ``w420nm`` … ``w720nm`` (reflectance)     10 nm (31)
           and ``R``, ``G``, ``B``
``cassi28`` the KAIST crops of the CASSI benchmarks (TSA-Net, DGSMP,   the benchmarks' 28
           MST): MATLAB ``.mat`` with ``img`` (``Truth/sceneNN.mat``,  centres, 453.5–648 nm
           256×256×28) or ``HSI`` (``KAIST_CVPR2021/N.mat``,
           2704×3376×28), values in [0, 1]
=========  ==========================================================  ======================

KAIST EXR
    The spectral channels are found by name, ``w<λ>nm``, and ordered by wavelength, never by
    position: an EXR stores its channels sorted by name, so position only works while every
    centre has three digits. The layout is that of the public loaders of the dataset, which
    read the ``w<λ>nm`` channels and skip ``R``, ``G``, ``B`` (e.g. ``loadexr`` with
    ``_KAIST_CHANNEL_NAMES = [f"w{w}nm" for w in range(420, 730, 10)]``; the
    ``read_exr_file_openexr`` of Deep-HSI-CASSI-Torch, which drops the first three sorted
    names, B, G, R; a reader checked against the first official file, ``w420nm`` …
    ``w660nm`` by name). ``R``, ``G``, ``B`` are not used: what camera and illuminant they
    render is not documented, so the pseudo-HDR-RGB of the cube stands in, as for the other
    datasets without an 8-bit RGB image. Values are reflectance (the dataset's name for the
    files), read as stored. The default band selection keeps the 29 bands in 420–700 nm,
    as for Harvard; nothing below 420 nm is made up.

CASSI 28-band cubes
    TSA-Net (Meng, Ma & Yuan 2020) resampled the KAIST scenes to the 28 wavelengths of its
    CASSI system, 453.5 … 648 nm; the later CASSI networks reuse those files and label their
    channels with that list (``lam28`` in MST's ``visualization/show_simulation.m`` and
    ``show_line.m``). MST's loaders read ``Truth/sceneNN.mat`` ``img`` as stored
    (``simulation/train_code/utils.py`` ``LoadTest``, scored on a [0, 1] scale) and
    ``KAIST_CVPR2021`` ``HSI`` (2704×3376×28) clipped to [0, 1] (``real/train_code/utils.py``
    ``prepare_data_KAIST``); both are read as stored here. The bands are not on a 10 nm grid:
    a model with 400:700:10 outputs cannot be scored on them (nothing is interpolated;
    :func:`mehs.ssr.pipeline.band_indices` says so), one trained on them can. The CAVE-derived
    files of the same benchmarks (``img_expand``, ``data_slice``, stored ×65535) are not read
    here; CAVE itself is (format ``cave``).

References
----------
- Choi, Jeon, Nam, Gutierrez & Kim (2017), "High-quality hyperspectral reconstruction using
  a spectral prior", ACM TOG 36(6) 218 (SIGGRAPH Asia); vclab.kaist.ac.kr/siggraphasia2017p1.
- Meng, Ma & Yuan (2020), "End-to-end low cost compressive spectral imaging with
  spatial-spectral self-attention", ECCV (TSA-Net).
- Cai et al. (2022), "Mask-guided spectral-wise transformer for efficient hyperspectral image
  reconstruction", CVPR (MST; github.com/caiyuanhao1998/MST).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import FormatError, InputError

#: The 28 band centres (nm) of the CASSI benchmarks' KAIST cubes (TSA-Net; MST ``lam28``).
CASSI28_BANDS = np.array([453.5, 457.5, 462.0, 466.0, 471.5, 476.5, 481.5, 487.0, 492.5, 498.0,
                          504.0, 510.0, 516.0, 522.5, 529.5, 536.5, 544.0, 551.5, 558.5, 567.5,
                          575.5, 584.5, 594.5, 604.0, 614.5, 625.0, 636.5, 648.0])
#: Variables of the CASSI cubes: ``img`` (TSA_simu_data ``Truth``), ``HSI`` (KAIST_CVPR2021).
CASSI28_KEYS = ("img", "HSI")


def kaist_channels(names) -> tuple[list[str], np.ndarray]:
    """The ``w<λ>nm`` channel names of ``names`` in wavelength order, and their centres (nm).

    Parsed by :func:`mehs.io.exr.parse_spectral_channel`, the one parser of spectral channel
    names that the generic spectral EXR reader uses too.
    """
    from mehs.io.exr import SCHEME_KAIST, parse_spectral_channel

    found = sorted((p[1], str(n)) for n in names for p in [parse_spectral_channel(str(n))]
                   if p and p[0] == SCHEME_KAIST)
    return [n for _, n in found], np.asarray([w for w, _ in found], dtype=np.float64)


def is_kaist_exr(path: str | Path) -> bool:
    """Whether ``path`` is an OpenEXR whose header names ``w<λ>nm`` channels (header only)."""
    import OpenEXR

    try:
        with open(path, "rb") as fh:
            if fh.read(4) != b"\x76\x2f\x31\x01":
                return False
        chans = OpenEXR.File(str(path), header_only=True).header().get("channels") or []
        # the header lists Channel objects (their names), a full read a name → Channel dict
        return bool(kaist_channels(getattr(c, "name", c) for c in chans)[0])
    except (OSError, RuntimeError, ValueError, TypeError, AttributeError):
        return False


def read_kaist(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A KAIST ``sceneNN_reflectance.exr`` → ``(cube float32 (H, W, B), bands (B,), info)``.

    ``B`` is the number of ``w<λ>nm`` channels (31 in the dataset), in wavelength order.

    Raises
    ------
    FormatError
        Not an OpenEXR file, unreadable, no ``w<λ>nm`` channel, two channels for one
        wavelength, sub-sampled or differently sized channels.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    with open(path, "rb") as fh:
        if fh.read(4) != b"\x76\x2f\x31\x01":
            raise FormatError("not an OpenEXR file (bad magic number)", path)
    try:
        chans = OpenEXR.File(str(path), separate_channels=True).channels()
    except (RuntimeError, ValueError, OSError) as exc:
        raise FormatError(f"cannot read the OpenEXR file ({exc})", path) from None
    names, bands = kaist_channels(chans)
    if not names:
        shown = sorted(chans)
        raise FormatError("no KAIST spectral channel (names like 'w420nm'); channels are "
                          f"{shown[:8]}{'…' if len(shown) > 8 else ''}", path)
    if np.unique(bands).size != bands.size:
        dup = sorted({n for n, w in zip(names, bands) if np.count_nonzero(bands == w) > 1})
        raise FormatError(f"channels {dup} name the same wavelength", path)
    first = np.asarray(chans[names[0]].pixels)
    cube = np.empty(first.shape + (len(names),), dtype=np.float32)
    for i, name in enumerate(names):
        ch = chans[name]
        if (getattr(ch, "xSampling", 1), getattr(ch, "ySampling", 1)) != (1, 1):
            raise FormatError(f"channel {name!r} is sub-sampled; not supported", path)
        plane = np.asarray(ch.pixels)
        if plane.shape != first.shape:
            raise FormatError(f"channel {name!r} is {plane.shape}, {names[0]!r} {first.shape}",
                              path)
        cube[:, :, i] = plane
    info: dict[str, Any] = {"channels": names, "units": "reflectance (as stored)",
                            "ignored_channels": sorted(set(chans) - set(names)),
                            "bands_from": "channel names w<λ>nm"}
    return cube, bands, info


def read_cassi28(path: str | Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A CASSI benchmark ``.mat`` (``img`` or ``HSI``) → ``(cube (H, W, 28), bands, info)``.

    Raises
    ------
    FormatError
        Neither variable, or not a real rows × columns × 28 array.
    """
    from mehs.io.matfile import read_mat_variables

    path = Path(path)
    cube, key, missing = None, None, []
    for k in CASSI28_KEYS:
        try:
            cube, key = read_mat_variables(path, (k,))[k], k
            break
        except FormatError as exc:
            if f"no variable {k!r}" not in exc.problem:
                raise
            missing.append(exc.problem)
    if cube is None:
        # read_mat_variables' message ends with the variables the file holds
        held = re.search(r"\((variables: .*)\)$", missing[-1])
        raise FormatError("no 'img' or 'HSI' cube of the CASSI benchmarks"
                          + (f" ({held.group(1)})" if held else ""), path)
    if cube.dtype.kind not in "fiub":
        raise FormatError(f"{key!r} must be real numbers, got {cube.dtype}", path)
    if cube.ndim != 3 or cube.shape[2] != CASSI28_BANDS.size:
        raise FormatError(f"{key!r} must be rows × columns × 28 bands (453.5–648 nm), got shape "
                          f"{cube.shape}", path)
    return cube, CASSI28_BANDS.copy(), {"variable": key,
                                        "bands_from": "CASSI 28-band list (TSA-Net; MST lam28)"}
