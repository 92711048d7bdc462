"""Spectral OpenEXR images: one channel per band (Fichet, Pacanowski & Wilkie 2021).

Split from :mod:`mehs.io.exr` (which re-exports these functions); the names of
spectral channels are parsed there, by :func:`mehs.io.exr.parse_spectral_channel`.

Spectral layout (Fichet, Pacanowski & Wilkie 2021)
    One channel per band named ``S0.<λ>nm`` for emissive data (radiance; the
    unpolarised Stokes component S0) or ``T.<λ>nm`` for reflectance /
    transmittance, where ``<λ>`` is the band centre in nm written with a comma
    as decimal separator and the shortest digits that round-trip exactly, e.g.
    ``S0.400nm``, ``S0.397,32nm``. Header attributes: ``spectralLayoutVersion
    = "1.0"`` (Fichet 2021), ``wavelengths`` (float vector, nm, band order),
    ``mehsWavelengths`` (the same as exact decimal text), ``mehsFWHM`` (text,
    when known), ``mehsUnits`` (the cube's units), ``mehsRadianceScale`` (when
    the values are radiance × a dataset's 2^-k). Readers that know the
    Fichet layout (colour-science ``read_spectral_image_Fichet2021``, the
    spectral-exr viewer, ART) read these files; the reader here also accepts
    bare ``<λ>nm`` and KAIST ``w<λ>nm`` channel names (one parser,
    :func:`mehs.io.exr.parse_spectral_channel`, shared with :mod:`mehs.io.ssr_kaist`), and
    refuses a file mixing naming schemes or naming one wavelength twice.

Units (``emissiveUnits``)
    The Fichet layout's ``emissiveUnits`` string says what ``S0`` values are;
    ``W.m^-2.sr^-1`` is the one spelling it defines (pbrt-v4, ART and
    colour-science write it; the reference reader assumes it when absent).
    mehs writes it only for calibrated absolute radiance stored as such
    (units ``W sr-1 m-2 nm-1``, no ``mehsRadianceScale`` other than 1), never
    for relative radiance, DN or radiance × 2^-k, whose values it would
    mislabel. Reading, ``mehsUnits`` wins; a file without it (another tool's)
    takes its units from ``emissiveUnits``. Files written before carry no
    ``emissiveUnits`` and read as before.

References
----------
- Fichet, A., Pacanowski, R., & Wilkie, A. (2021). An OpenEXR Layout for
  Spectral Images. JCGT 10(3). http://jcgt.org/published/0010/03/01/
  (``emissiveUnits``: also the spectral-exr reference reader, pbrt-v4's
  ``SpectralFilm``, colour-science ``write_spectral_image_Fichet2021``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.io.exr import (BISPECTRAL_RE, SCHEME_BARE, SCHEME_KAIST, parse_spectral_channel,
                         read_exr, write_exr)

#: mehs's unit of absolute spectral radiance (= :data:`mehs.calibration.UNIT_ABSOLUTE`).
ABSOLUTE_RADIANCE = "W sr-1 m-2 nm-1"
#: Fichet 2021 ``emissiveUnits`` of absolute (spectral) radiance, as pbrt-v4, ART and
#: colour-science write it; the reference reader (spectral-exr) knows no other.
EMISSIVE_UNITS = "W.m^-2.sr^-1"
# spellings read as absolute spectral radiance: the convention's, and with the per-nm
# made explicit (TinyEXR's spectral tests write it so)
_EMISSIVE_ABSOLUTE = ("W.m^-2.sr^-1", "W.m^-2.sr^-1.nm^-1")
_ABSOLUTE_SPELLINGS = ("w sr-1 m-2 nm-1", "w m-2 sr-1 nm-1", "w/(m2 sr nm)", "w.m^-2.sr^-1",
                       "w.m^-2.sr^-1.nm^-1", "w sr⁻¹ m⁻² nm⁻¹")


def wavelength_channel_name(wavelength_nm: float, component: str = "S0") -> str:
    """Fichet 2021 channel name of one band, e.g. ``S0.400nm`` or ``T.397,32nm``."""
    wl = float(wavelength_nm)
    text = str(int(wl)) if wl.is_integer() else repr(wl)
    return f"{component}.{text.replace('.', ',')}nm"


def write_exr_spectral(path: str | Path, cube: Any, wavelengths: Sequence[float] | None = None, *,
                       half: bool = False, header: dict[str, Any] | None = None,
                       name: str | Path | None = None) -> Path:
    """Write a spectral image as one EXR channel per band (Fichet 2021 layout).

    Parameters
    ----------
    cube
        A :class:`~mehs.cube.SpectralCube` or an ``(H, W, B)`` array (then
        ``wavelengths`` is required). A cube's lines become image rows.
    wavelengths
        Band centres in nm, ``(B,)``; overrides the cube's when given.
    half
        Store half floats (values beyond ±65504 raise).
    name
        The file to name in errors and warnings when ``path`` is a temporary one
        (:func:`mehs.io.exr.write_exr`).

    Channels are ``S0.<λ>nm`` (``T.<λ>nm`` when the cube's units say
    reflectance); see the module docstring for the header attributes
    (``emissiveUnits`` only for absolute radiance as stored; a cube's
    ``mehs radiance scale`` becomes ``mehsRadianceScale``).
    """
    from mehs.cube import SpectralCube, validate_wavelengths

    path = Path(path)
    where = Path(name) if name is not None else path
    units = "relative radiance"
    fwhm = scale = None
    if isinstance(cube, SpectralCube):
        data = cube.data
        wl = cube.wavelengths if wavelengths is None else wavelengths
        units = cube.units
        fwhm = cube.fwhm if wavelengths is None else None
        from mehs.export import radiance_scale

        scale = radiance_scale(cube)  # stored = radiance × scale (a dataset's 2^-k)
    else:
        data = np.asarray(cube)
        if wavelengths is None:
            raise InputError("wavelengths are required to write an array as a spectral EXR", where)
        wl = wavelengths
    if data.ndim != 3:
        raise InputError(f"a spectral image must be (H, W, B), got shape {data.shape}", where)
    wl = validate_wavelengths(wl, data.shape[2], where)
    component = "T" if "reflect" in str(units).lower() or "transmit" in str(units).lower() else "S0"
    names = [wavelength_channel_name(w, component) for w in wl]
    hdr: dict[str, Any] = {
        "spectralLayoutVersion": "1.0",
        "wavelengths": [float(w) for w in wl],
        "mehsWavelengths": " ".join(repr(float(w)) for w in wl),
        "mehsUnits": str(units),
    }
    if fwhm is not None:
        hdr["mehsFWHM"] = " ".join(repr(float(f)) for f in fwhm)
    if scale is not None:
        hdr["mehsRadianceScale"] = float(scale)
    if header:
        hdr.update(header)
    stored_scale = hdr.get("mehsRadianceScale")
    if (component == "S0" and "emissiveUnits" not in hdr and _emissive_units_for(units)
            and (stored_scale is None or float(stored_scale) == 1.0)):
        # Fichet's readers take S0 values for W.m^-2.sr^-1 (the reference one assumes it when
        # the attribute is absent): say so only when it is true, i.e. calibrated absolute
        # radiance as stored; relative radiance, or radiance × 2^-k, carry no emissiveUnits
        hdr["emissiveUnits"] = EMISSIVE_UNITS
    return write_exr(path, data, names, half=half, header=hdr, name=name)


def _spectral_groups(channels: Sequence[str]) -> dict[str, list[tuple[int, float]]]:
    found: dict[str, list[tuple[int, float]]] = {}
    for i, name in enumerate(channels):
        parsed = parse_spectral_channel(name)
        if parsed and parsed[0] not in ("S1", "S2", "S3"):
            found.setdefault(parsed[0], []).append((i, parsed[1]))
    return found


#: Which group of spectral channels a reader takes, first found first.
_SCHEME_PRIORITY = ("S0", "T", SCHEME_BARE, SCHEME_KAIST)


def spectral_channels(channels: Sequence[str]) -> tuple[list[int], np.ndarray]:
    """Indices and wavelengths (nm) of the emissive/reflective spectral channels.

    Recognises Fichet 2021 names (``S0.<λ>nm``, ``T.<λ>nm``, a wavelength in ``m`` or a
    frequency in ``Hz`` with any SI prefix; comma or point decimal), bare ``<λ>nm`` and KAIST's
    ``w<λ>nm`` (:func:`parse_spectral_channel`). Polarised components
    ``S1``–``S3`` are skipped. When both ``S0`` and ``T`` channels exist, ``S0``
    (emission) wins (a Fichet file may hold both). Lenient (for summaries):
    :func:`read_exr_spectral` also refuses mixed schemes and repeated wavelengths.
    """
    found = _spectral_groups(channels)
    for comp in _SCHEME_PRIORITY:
        if comp in found:
            idx, wl = zip(*found[comp])
            return list(idx), np.asarray(wl, dtype=np.float64)
    return [], np.empty(0)


def checked_spectral_channels(channels: Sequence[str], path=None) -> tuple[list[int], np.ndarray,
                                                                            str]:
    """:func:`spectral_channels` for reading a cube, with the scheme taken (``"S0"``,
    ``"T"``, ``""`` bare, ``"w"`` KAIST).

    Raises
    ------
    FormatError
        (naming ``path``) Channels of two naming schemes other than Fichet's ``S0`` + ``T``
        pair (``S0.400nm`` beside ``400nm`` or ``w400nm``: which is the image is a guess),
        or two channels of the taken scheme for one wavelength (``S0.400nm`` and
        ``S0.400,0nm``: the cube would hold one band twice).
    """
    found = _spectral_groups(channels)
    schemes = [c for c in _SCHEME_PRIORITY if c in found]
    rerad = [c for c in channels if BISPECTRAL_RE.match(str(c))]
    if rerad and schemes:
        import warnings

        # a fluorescent sample's re-radiation matrix has no place in a cube; its diagonal
        # (T.<λ>) is the reflectance without fluorescence, which is what is read
        warnings.warn(f"{path}: {len(rerad)} bi-spectral re-radiation channels "
                      f"({rerad[0]!r} …) are ignored: the cube holds the diagonal "
                      "(non-fluorescent) reflectance only", UserWarning, stacklevel=3)
    elif rerad:
        raise FormatError(f"only bi-spectral re-radiation channels ({rerad[0]!r} …, "
                          f"{len(rerad)} channels) and no T.<λ> diagonal: not a cube", path)
    if len(schemes) > 1 and set(schemes) != {"S0", "T"}:
        def show(c):
            return f"{channels[found[c][0][0]]!r} ({len(found[c])} channels)"

        raise FormatError("spectral channels of more than one naming scheme: "
                          f"{', '.join(show(c) for c in schemes)}; which of them is the image "
                          "is ambiguous", path)
    if not schemes:
        return [], np.empty(0), ""
    idx, wl = (list(v) for v in zip(*found[schemes[0]]))
    wla = np.asarray(wl, dtype=np.float64)
    # the same centre written two ways (S0.400nm, S0.400,0nm, S0.0,4um)
    _, inverse, counts = np.unique(np.round(wla, 6), return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        dup = [channels[i] for i, k in zip(idx, inverse) if counts[k] > 1]
        raise FormatError(f"channels {dup} name the same wavelength", path)
    return idx, wla, schemes[0]


def _text_floats(value: Any, n: int) -> np.ndarray | None:
    if not isinstance(value, str):
        return None
    try:
        out = np.asarray([float(v) for v in value.split()], dtype=np.float64)
    except ValueError:
        return None
    return out if out.size == n else None


def _emissive_units_for(units: str) -> str | None:
    """The Fichet ``emissiveUnits`` of a cube's ``units``: :data:`EMISSIVE_UNITS` for
    absolute spectral radiance, ``None`` for anything else (relative, DN, reflectance)."""
    u = " ".join(str(units).replace("·", " ").split()).lower()
    return EMISSIVE_UNITS if u in _ABSOLUTE_SPELLINGS else None


def read_exr_spectral(path: str | Path):
    """Read a spectral EXR (Fichet 2021 layout, bare ``<λ>nm`` or KAIST ``w<λ>nm`` channels).

    Returns
    -------
    SpectralCube
        float32 data ``(H, W, B)`` (rows → lines), wavelengths from the
        exact ``mehsWavelengths`` attribute when present and consistent, else
        from the channel names; units from ``mehsUnits``, else from the Fichet
        ``emissiveUnits`` of ``S0`` channels (``W.m^-2.sr^-1`` → absolute
        radiance, :data:`ABSOLUTE_RADIANCE`), else ``"reflectance"`` for ``T.``
        and KAIST ``w`` channels (the KAIST files are reflectance) and
        ``"relative radiance"`` otherwise. ``metadata`` keeps the channel names,
        ``emissiveUnits`` when given, and the stored factor of ``mehsRadianceScale``
        as ``"mehs radiance scale"`` (stored = radiance × scale), so a cube read here
        and written again keeps it. Non-spectral channels (e.g. an ``R, G, B``
        preview) are ignored.

    Raises
    ------
    FormatError
        No spectral channels, channels of two naming schemes, two channels for one
        wavelength, a malformed ``mehsRadianceScale``.
    """
    from mehs.cube import SpectralCube
    from mehs.export import parse_radiance_scale

    img = read_exr(path, check_finite=True)
    idx, wl, scheme = checked_spectral_channels(img.channels, img.path)
    if not idx:
        raise FormatError(
            f"no spectral channels (expected names like 'S0.400nm'); channels are "
            f"{img.channels[:8]}{'…' if len(img.channels) > 8 else ''}", img.path)
    exact = _text_floats(img.header.get("mehsWavelengths"), len(idx))
    if exact is not None and np.allclose(exact, wl, rtol=0, atol=1e-3):
        wl = exact
    metadata: dict[str, Any] = {"exr_channels": [img.channels[i] for i in idx]}
    emissive = img.header.get("emissiveUnits")
    if isinstance(emissive, bytes):
        emissive = emissive.decode("utf-8", "replace")
    if isinstance(emissive, str) and scheme == "S0":
        metadata["emissiveUnits"] = emissive
    scale = parse_radiance_scale(img.header.get("mehsRadianceScale"), img.path)
    if scale is not None:
        metadata["mehs radiance scale"] = repr(scale)
    units = img.header.get("mehsUnits")
    if not isinstance(units, str):
        if "emissiveUnits" in metadata:
            # the convention's spelling of absolute radiance (pbrt-v4, ART, colour-science)
            units = (ABSOLUTE_RADIANCE if emissive.replace(" ", "") in _EMISSIVE_ABSOLUTE
                     else emissive)
        else:
            units = "reflectance" if scheme in ("T", SCHEME_KAIST) else "relative radiance"
    fwhm = _text_floats(img.header.get("mehsFWHM"), len(idx))
    data = img.data if idx == list(range(img.data.shape[2])) else img.data[:, :, idx]
    return SpectralCube(data=np.ascontiguousarray(data), wavelengths=wl, fwhm=fwhm, units=units,
                        source=img.path, metadata=metadata)
