"""Spectral resampling of cubes to a target band set (default 400–700 nm, 10 nm, 31 bands).

Every method builds one matrix ``M`` of shape ``(n_dst, n_src)`` whose rows
sum to 1 (so a flat spectrum stays flat); a cube is resampled as
``cube @ M.T`` in float32, chunked over lines so memory-mapped cubes are
streamed, using only the source bands that some target band sees.

Methods (:data:`RESAMPLING_METHODS`)
    ``gaussian`` (default)
        The construction of SPy's ``spectral.BandResampler``: each source band
        is taken as constant over ``centre ± FWHM/2``; each target band has a
        Gaussian response of the given FWHM, considered over its own
        ``centre ± FWHM/2`` window. The weight of source band *j* in target
        band *i* is the Gaussian's integral over the overlap of the two
        windows, then rows are normalised. Source FWHMs default (as in SPy) to
        half the distance between a band's two neighbours. The response is thus
        cut at its half maximum (σ ≈ 2.6 nm for 10 nm FWHM, not 4.25 nm): on
        line spectra (colour's HP1) it differs from a full Gaussian by up to
        ~35 %, on smooth ones (D65) by ~1.5 % — SPy's method, kept on purpose.
    ``linear``
        Linear interpolation between the two source bands around each target
        centre (exact for spectra linear in wavelength). Needs the target
        inside the source range.
    ``box``
        Average of the source bands weighted by the length of their overlap
        (``centre ± FWHM/2`` each) with a rectangular window of width FWHM
        around the target centre.

A target band that no source band reaches raises :class:`InputError` naming
the band; a target band whose Gaussian window is less than half covered gets a
:class:`PartialCoverageWarning`. Source bands outside every target window
get zero weight and are never read.

Bands an ENVI ``bbl`` flags bad are left out (``exclude``): each target is made
from the good bands that reach it (for ``linear``: interpolated between the
nearest good bands), as ENVI's bad-band list asks of processing. A target
that only bad bands reach is made from them and flagged bad in the output
``bbl`` (with a warning), as is one whose window lies mostly in bad bands.
Samples equal to the header's ``data ignore value`` (NaN allowed) are no
data: every target value that would draw on one is the ignore value.

References
----------
- Boggs, T. et al. Spectral Python (SPy), ``spectral.algorithms.resampling.
  BandResampler`` / ``create_resampling_matrix``.
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

from mehs.bandmeta import bad_bands, resampled_band_metadata
from mehs._blas import single_thread_blas
from mehs.cube import SpectralCube, validate_wavelengths
from mehs.errors import InputError, MehsError
from mehs.rgb import WAVELENGTHS_31

#: FWHM = SIGMA_PER_FWHM · σ for a Gaussian.
SIGMA_PER_FWHM = 2.0 * np.sqrt(2.0 * np.log(2.0))

#: Target bytes of float32 input per processing chunk (lines are grouped to this size).
CHUNK_BYTES = 32 << 20


class PartialCoverageWarning(UserWarning):
    """A target band's window is only partly covered by source bands."""


def default_fwhm(centres: np.ndarray) -> np.ndarray:
    """SPy's default band widths: half the distance between each band's neighbours.

    ``centres`` must be sorted ascending; shape ``(n,)`` → ``(n,)``.
    """
    c = np.asarray(centres, dtype=np.float64)
    if c.size == 1:
        raise InputError("one band without a FWHM: its width is unknown; give src_fwhm")
    f = np.empty_like(c)
    f[0] = c[1] - c[0]
    f[-1] = c[-1] - c[-2]
    f[1:-1] = (c[2:] - c[:-2]) / 2.0
    return f


def _per_band(value, n: int, what: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)) if np.ndim(value) == 0 \
        else np.asarray(value, dtype=np.float64).reshape(-1)
    if v.size != n:
        raise InputError(f"{v.size} {what} values for {n} bands")
    if not np.all(np.isfinite(v) & (v > 0)):
        raise InputError(f"{what} values must be finite and positive")
    return np.array(v, dtype=np.float64)


def _overlap(src_c, src_f, dst_c, dst_f):
    """Lower/upper bounds ``(n_dst, n_src)`` of the overlap of the two window sets."""
    lo = np.maximum((src_c - src_f / 2)[None, :], (dst_c - dst_f / 2)[:, None])
    hi = np.minimum((src_c + src_f / 2)[None, :], (dst_c + dst_f / 2)[:, None])
    return lo, hi


def _matrix_gaussian(src_c, src_f, dst_c, dst_f):
    from scipy.special import ndtr

    lo, hi = _overlap(src_c, src_f, dst_c, dst_f)
    sigma = (dst_f / SIGMA_PER_FWHM)[:, None]
    w = np.where(hi > lo, ndtr((hi - dst_c[:, None]) / sigma) - ndtr((lo - dst_c[:, None]) / sigma),
                 0.0)
    full = ndtr(SIGMA_PER_FWHM / 2) - ndtr(-SIGMA_PER_FWHM / 2)
    return w, w.sum(axis=1) / full


def _matrix_box(src_c, src_f, dst_c, dst_f):
    lo, hi = _overlap(src_c, src_f, dst_c, dst_f)
    w = np.clip(hi - lo, 0.0, None)
    return w, w.sum(axis=1) / dst_f


def _matrix_linear(src_c, src_f, dst_c, dst_f):
    n_dst, n_src = dst_c.size, src_c.size
    w = np.zeros((n_dst, n_src))
    inside = (dst_c >= src_c[0]) & (dst_c <= src_c[-1])
    if n_src == 1:
        w[inside, 0] = 1.0
        return w, inside.astype(float)
    j = np.clip(np.searchsorted(src_c, dst_c, side="right") - 1, 0, n_src - 2)
    t = (dst_c - src_c[j]) / (src_c[j + 1] - src_c[j])
    rows = np.flatnonzero(inside)
    w[rows, j[rows]] = 1.0 - t[rows]
    w[rows, j[rows] + 1] += t[rows]
    return w, inside.astype(float)


#: method name → builder ``(src_c, src_f, dst_c, dst_f) -> (weights, coverage)`` on sorted sources.
RESAMPLING_METHODS: dict[str, Callable] = {
    "gaussian": _matrix_gaussian,
    "linear": _matrix_linear,
    "box": _matrix_box,
}


def resampling_matrix(src_wl, dst_wl=WAVELENGTHS_31, *, method: str = "gaussian",
                      src_fwhm=None, dst_fwhm=10.0, exclude=None) -> np.ndarray:
    """Resampling matrix ``M`` so that ``dst = M @ src`` for one spectrum.

    Parameters
    ----------
    src_wl
        Source band centres in nm, ``(n_src,)``, any order (columns of ``M``
        follow this order).
    dst_wl
        Target band centres in nm, ``(n_dst,)``; rows of ``M`` follow it.
    method
        A key of :data:`RESAMPLING_METHODS`.
    src_fwhm
        Source FWHMs in nm (scalar or ``(n_src,)``); default: SPy's rule.
    dst_fwhm
        Target FWHM in nm (scalar or ``(n_dst,)``); unused by ``linear``.
    exclude
        Optional bool ``(n_src,)``: source bands to leave out (flagged bad).
        Their columns are zero except in rows no other band reaches.

    Returns
    -------
    ndarray
        float64 ``(n_dst, n_src)``, every row summing to 1.

    Raises
    ------
    InputError
        Unknown method, bad wavelengths/FWHMs, or a target band with no
        source coverage (the message names it).
    """
    return _matrices(src_wl, dst_wl, method, src_fwhm, dst_fwhm, exclude)[1]


def _matrices(src_wl, dst_wl, method, src_fwhm, dst_fwhm, exclude):
    """``(m_all, m_used)``: the matrix of all source bands and the one without
    the ``exclude``d bands (rows only they reach keep ``m_all``'s weights)."""
    if method not in RESAMPLING_METHODS:
        raise InputError(f"unknown resampling method {method!r}; "
                         f"choose one of {sorted(RESAMPLING_METHODS)}")
    src = validate_wavelengths(src_wl)
    dst = validate_wavelengths(dst_wl)
    order = np.argsort(src, kind="stable")
    src_c = src[order]
    if src_fwhm is None:
        src_f = default_fwhm(src_c)
    else:
        src_f = _per_band(src_fwhm, src.size, "source FWHM")[order]
    dst_f = _per_band(dst_fwhm, dst.size, "target FWHM")
    build = RESAMPLING_METHODS[method]

    w, coverage = build(src_c, src_f, dst, dst_f)
    sums = w.sum(axis=1)
    empty = np.flatnonzero(sums <= 0)
    if empty.size:
        # A header in µm read as nm puts the whole sensor below 3 nm.
        hint = (" — are the wavelengths in micrometres? mehs expects nm"
                if src_c[-1] < 30.0 <= dst.max() else "")
        span = f"the source bands span {src_c[0]:g}..{src_c[-1]:g} nm"
        if empty.size == dst.size:
            # e.g. an FX17 (900–1700 nm) resampled to 400–700 nm: no band in common at all
            raise InputError(
                f"no source band covers {dst[0]:g}–{dst[-1]:g} nm: the {dst.size} target "
                f"band(s) have no source coverage ({span}, method {method!r}){hint}")
        names = ", ".join(f"{dst[i]:g} nm" for i in empty[:6])
        more = f" … ({empty.size} of {dst.size})" if empty.size > 6 else ""
        raise InputError(
            f"target band(s) {names}{more} have no source coverage ({span}, "
            f"method {method!r}){hint}")
    partial = np.flatnonzero(coverage < 0.5)
    if partial.size and method != "linear":
        warnings.warn(
            "target band(s) " + ", ".join(f"{dst[i]:g} nm" for i in partial[:6])
            + " are less than half covered by source bands", PartialCoverageWarning, stacklevel=3)
    w_all = w / sums[:, None]
    w_used = w_all
    if exclude is not None:
        bad = np.asarray(exclude, dtype=bool).reshape(-1)
        if bad.size != src.size:
            raise InputError(f"{bad.size} exclude flags for {src.size} bands")
        good = ~bad[order]
        if good.any() and not good.all():
            # Widths stay those of the full band set (a flagged band still occupies
            # its slot); only its weight goes. For linear this interpolates across it.
            wg = np.zeros_like(w)
            wg[:, good] = build(src_c[good], src_f[good], dst, dst_f)[0]
            gsum = wg.sum(axis=1)
            only_bad = np.flatnonzero(gsum <= 0)
            if only_bad.size:
                warnings.warn(
                    "target band(s) " + ", ".join(f"{dst[i]:g} nm" for i in only_bad[:6])
                    + " are reached only by bands flagged bad (bbl); made from them and "
                    "flagged bad", PartialCoverageWarning, stacklevel=3)
            w_used = np.where((gsum > 0)[:, None], wg / np.where(gsum > 0, gsum, 1.0)[:, None],
                              w_all)
    out = []
    for m_sorted in (w_all, w_used):
        m = np.empty_like(m_sorted)
        m[:, order] = m_sorted
        out.append(m)
    return out[0], out[1]


def parse_bands(spec: str) -> np.ndarray:
    """Target wavelengths from ``"start:stop:step"`` (stop included) or ``"w1,w2,…"`` (nm)."""
    text = str(spec).strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3 or parts[2] <= 0 or parts[1] < parts[0]:
                raise ValueError
            if not np.all(np.isfinite(parts)):
                raise ValueError  # int(inf) below would be an OverflowError
            start, stop, step = parts
            n = int(np.floor((stop - start) / step + 1e-9)) + 1
            return start + step * np.arange(n)
        out = np.asarray([float(p) for p in text.split(",") if p.strip()], dtype=np.float64)
        if not np.all(np.isfinite(out)):
            raise ValueError
        return out
    except (ValueError, OverflowError, MemoryError):
        raise InputError(f"cannot parse bands {spec!r}; use start:stop:step "
                         "(e.g. 400:700:10) or a comma-separated list") from None


def apply_matrix(data: np.ndarray, matrix: np.ndarray, *, chunk_lines: int | None = None,
                 source=None, ignore: float | None = None) -> np.ndarray:
    """``data @ matrix.T`` in float32, chunked over lines.

    Parameters
    ----------
    data
        ``(lines, samples, n_src)`` array or memmap, any real dtype.
    matrix
        ``(n_dst, n_src)``.
    chunk_lines
        Lines per chunk; default: about :data:`CHUNK_BYTES` of float32 input.
    ignore
        The no-data marker (ENVI ``data ignore value``; NaN allowed): a target
        value drawing on a sample equal to it is set to it exactly, rather
        than mixed into a number that no longer reads as no data.

    Returns
    -------
    ndarray
        float32 ``(lines, samples, n_dst)``.

    Raises
    ------
    InputError
        When the result holds NaN/Inf (non-finite input in a used band that
        is not the ``ignore`` marker).
    """
    lines, samples, n_src = data.shape
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape[1] != n_src:
        raise InputError(f"matrix expects {matrix.shape[1]} bands, data has {n_src}", source)
    used = np.flatnonzero(np.any(matrix != 0, axis=0))
    # A contiguous band range is read as a strided view; anything else is gathered.
    if used.size and used[-1] - used[0] + 1 == used.size:
        sel = slice(int(used[0]), int(used[-1]) + 1)
    else:
        sel = used
    mt = np.ascontiguousarray(matrix[:, used].T, dtype=np.float32)
    n_dst = matrix.shape[0]
    out = np.empty((lines, samples, n_dst), dtype=np.float32)
    if chunk_lines is None:
        chunk_lines = max(1, CHUNK_BYTES // max(1, samples * used.size * 4))
    # BIL/BSQ memmaps are transposed views whose samples axis is the fastest:
    # multiply band-major there (M @ (bands, samples) per line), which BLAS takes
    # without copying; a (samples, bands) product on such a view is ~20× slower.
    band_major = data.strides[2] > data.strides[1] if samples > 1 else False
    m_band = np.ascontiguousarray(mt.T)
    nz_band = (m_band != 0).astype(np.float32)  # which used band feeds which target
    marker = None if ignore is None else np.float32(ignore)
    bad_lines: list[np.ndarray] = []
    # NaN/Inf are reported once, below, as an InputError naming the lines; numpy's
    # per-block RuntimeWarning before it would only be noise.
    # one BLAS thread: hundreds of small products, which 2+ spin-waiting threads
    # stall on whenever another process holds a core (mehs._blas)
    with np.errstate(invalid="ignore", over="ignore"), single_thread_blas():
        for l0 in range(0, lines, chunk_lines):
            l1 = min(lines, l0 + chunk_lines)
            block = np.asarray(data[l0:l1, :, sel])
            if band_major:
                block = block.transpose(0, 2, 1)
                if block.dtype != np.float32:
                    block = block.astype(np.float32)  # keeps the band-major order
                res = np.matmul(m_band, block)                    # (l, n_dst, samples)
            else:
                if block.dtype != np.float32:
                    block = block.astype(np.float32)
                res = np.matmul(block, mt, out=out[l0:l1])      # (l, samples, n_dst)
            no_data = None
            if marker is not None:
                hit = np.isnan(block) if np.isnan(marker) else block == marker
                if hit.any():
                    # targets whose weights touch a no-data sample (band axis summed)
                    no_data = (np.matmul(nz_band, hit.astype(np.float32)) if band_major
                               else np.matmul(hit.astype(np.float32), nz_band.T)) > 0
                    res[no_data] = marker
            finite = np.isfinite(res)
            if no_data is not None:
                finite |= no_data
            if not finite.all():
                bad_lines.append(l0 + np.unique(np.argwhere(~finite)[:, 0]))
            if band_major:
                out[l0:l1] = res.transpose(0, 2, 1)
    if bad_lines:
        bad = np.concatenate(bad_lines)
        raise InputError(f"the cube holds NaN/Inf values in the bands used (lines "
                         f"{bad[:5].tolist()}{'…' if bad.size > 5 else ''})", source)
    return out


def _ignore_value(cube: SpectralCube) -> float | None:
    """The cube's ENVI ``data ignore value`` as a number (NaN allowed), or None."""
    v = (cube.metadata or {}).get("data ignore value")
    if v is None or str(v).strip() == "":
        return None
    try:
        return float(str(v).strip())
    except ValueError:
        raise InputError(f"'data ignore value' {v!r} is not a number", cube.source) from None


def resample_cube(cube: SpectralCube, target=WAVELENGTHS_31, *, method: str = "gaussian",
                  fwhm=10.0, chunk_lines: int | None = None) -> SpectralCube:
    """Resample a cube to ``target`` band centres.

    Parameters
    ----------
    cube
        Source cube ``(lines, samples, n_src)``; its ``fwhm`` is used when set,
        its ``bbl`` bad bands are left out and samples equal to its ``data
        ignore value`` stay no data (module docstring).
    target
        Target centres in nm, default :data:`mehs.rgb.WAVELENGTHS_31`; any
        order (the result is sorted, each FWHM kept with its centre).
    method
        ``"gaussian"``, ``"linear"`` or ``"box"`` (:data:`RESAMPLING_METHODS`).
    fwhm
        Target FWHM in nm (scalar or per band).

    Returns
    -------
    SpectralCube
        float32 ``(lines, samples, n_dst)`` with the source's metadata, the
        target wavelengths, ``fwhm`` set to the target FWHM (``None`` for
        ``linear``), ``default_bands`` moved to the nearest target bands (dropped
        when one lies outside the target range), a recomputed ``bbl`` (when the
        source had one), ``metadata["resampling method"]``, ``["resampling
        fwhm"]`` (nm) and ``["resampling source fwhm"]`` (``"header"``, or that
        SPy's width rule was assumed).
    """
    dst = validate_wavelengths(target)  # a bad target is the option's fault, not the file's
    order = np.argsort(dst, kind="stable")
    dst = dst[order]  # a per-band FWHM (and its header list) must follow its centre
    fw = fwhm if np.ndim(fwhm) == 0 else _per_band(fwhm, dst.size, "target FWHM")[order]
    bad_src = bad_bands(cube.metadata, cube.bands)
    try:
        m_all, m = _matrices(cube.wavelengths, dst, method, cube.fwhm, fw, bad_src)
    except MehsError as exc:  # e.g. no coverage: name the cube's file
        raise exc.with_path(cube.source) from None
    data = apply_matrix(cube.data, m, chunk_lines=chunk_lines, source=cube.source,
                        ignore=_ignore_value(cube))
    default = None
    if cube.default_bands is not None:
        src_wl = cube.wavelengths[list(cube.default_bands)]
        half = 0.5 * (np.max(fw) if method != "linear" else
                      (np.max(np.diff(dst)) if dst.size > 1 else 0.0))
        # A NIR false-colour composite has no counterpart on 400..700 nm; the nearest
        # target (700 nm) would silently make it another composite.
        if np.all((src_wl >= dst[0] - half) & (src_wl <= dst[-1] + half)):
            default = tuple(int(np.argmin(np.abs(dst - w))) for w in src_wl)
    dst_f = None if method == "linear" else _per_band(fw, dst.size, "target FWHM")
    # bbl recomputed from the weights; names/gains/offsets of the source bands dropped
    meta = resampled_band_metadata(cube.metadata, m_all, m)
    # Flat text/number keys so ENVI headers can carry them.
    meta["resampling method"] = method
    meta.pop("resampling fwhm", None)
    if dst_f is not None:
        meta["resampling fwhm"] = float(dst_f[0]) if np.all(dst_f == dst_f[0]) else dst_f.tolist()
    meta["resampling source fwhm"] = ("header" if cube.fwhm is not None else
                                      "assumed: band spacing (SPy rule)")
    return cube.with_data(data, wavelengths=dst, fwhm=dst_f, default_bands=default,
                          metadata=meta)
