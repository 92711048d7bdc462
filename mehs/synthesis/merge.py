"""Merging a bracket of exposures into one float32 radiance cube.

Every method works sample by sample on the dark-subtracted values
``y_j = raw_j − dark_j`` (linear sensor) or ``y_j = exp(g(round(raw_j − dark_j)))``
(a recovered response curve), with exposure times ``t_j`` in ms:

- ``debevec``  (:func:`merge_Debevec1997`): ``ln X = Σ w(z_j)(g(z_j) − ln t_j) / Σ w(z_j)``;
- ``robertson`` (:func:`merge_Robertson2003`): ``X = Σ w(z_j) t_j y_j / Σ w(z_j) t_j²``
  (for a linear sensor ``w`` is taken at the expected level ``X₀·t_j``, not the
  noisy one, which would favour upward noise);
- ``poisson``  (:func:`merge_Hanji2020`): ``X = Σ y_j / Σ t_j`` over the usable samples —
  the maximum-likelihood estimate for Poisson (photon) noise;
- ``inverse-variance`` (:func:`merge_inverse_variance`): ``X = Σ ω_j y_j/t_j / Σ ω_j`` with
  ``ω_j = t_j² / (gain·X₀t_j + σ_read²)``, the variance predicted from the pooled
  (Poisson) estimate ``X₀`` rather than from the noisy ``y_j`` itself, which would
  bias the result low.

A sample is *usable* when its raw DN is below the saturation level (per band)
and — for exposures after the shortest — the running estimate of the shorter
exposures predicts it at least 3σ below saturation. The choice never depends
on the sample's own noise: dropping samples because *they* are low (a noise
floor) or high (just under saturation) biases each exposure's estimate and
makes static pixels fail the consistency test. Only ``debevec`` (``ln y``)
needs ``y_j`` above a floor. A band saturated in every exposure gets
the lower bound ``y_0/t_0`` of the shortest exposure and the pixel is flagged
(mask bit 1), never extrapolated; a pixel with no usable sample in any band is
flagged "no signal" (bit 4). Output radiance is in DN/ms (relative units), or
absolute after multiplying by a radiometric calibration factor (scalar or per band).
Negative estimates (dark noise around a near-zero radiance) are clipped to 0 by
default (``clip_negative``); the clipping bias is measurable only where the
signal is of the order of the noise (on the demo scenes it changes no median).

The compiled kernels (:mod:`mehs.synthesis._merge_fused` and
:mod:`mehs.synthesis._merge_fused_weighted`: a linear sensor's merges with the hat
weighting, in one pass per sample; :mod:`mehs.synthesis._merge_kernels`: a non-linear
sensor's, and other weightings) process a chunk of lines at a time
straight from the (memory-mapped) inputs, in their native memory order, on a
thread pool, and also accumulate the per-pixel consistency statistic used by
:mod:`mehs.synthesis.ghost`.

References
----------
- Debevec, P. E. and Malik, J. (1997). Recovering high dynamic range radiance
  maps from photographs. SIGGRAPH 97.
- Robertson, M. A., Borman, S. and Stevenson, R. L. (2003). Estimation-theoretic
  approach to dynamic range enhancement using multiple exposures. J. Electronic
  Imaging 12(2), 219–228.
- Hanji, P., Zhong, F., Mantiuk, R. K. and Mantiuk, R. (2020). Noise-aware
  merging of high dynamic range image stacks without camera calibration.
  ECCV 2020 Workshops.
- Granados, M., Ajdin, B., Wand, M., Theobalt, C., Seidel, H.-P. and Lensch,
  H. P. A. (2010). Optimal HDR reconstruction with linear digital cameras. CVPR.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from mehs.errors import InputError
from mehs.synthesis.merge_types import (AUTO_BINS_MAX_EXPOSURES, AUTO_BINS_MIN_BANDS,
                                        AUTO_CONSISTENCY_BINS, BINNED_MAX_EXPOSURES,
                                        MASK_GHOST, MASK_INVALID, MASK_SATURATED, MergeResult,
                                        NoiseModel, auto_consistency_bins,
                                        consistency_bins_value)
from mehs.synthesis.response import ResponseCurve, weighting_table

# the types and the ghost-bins rule live in merge_types; callers import them from here
__all__ = ["AUTO_BINS_MAX_EXPOSURES", "AUTO_BINS_MIN_BANDS", "AUTO_CONSISTENCY_BINS",
           "MASK_GHOST", "MASK_INVALID", "MASK_SATURATED", "MERGE_METHODS", "MergeResult",
           "NoiseModel", "merge_Debevec1997", "merge_Hanji2020", "merge_Robertson2003",
           "merge_bracket", "merge_inverse_variance", "warm_merge_kernel"]

#: Most bytes of input one merge chunk copies (all exposures) when it cannot read in place.
COPY_CHUNK_BYTES = 16 << 20

_CODES = {"debevec": 0, "robertson": 1, "poisson": 2, "inverse-variance": 3}


#: the one-pass kernel of each weighted method (linear curve, hat weighting)
_WEIGHTED_KINDS = {_CODES["debevec"]: "debevec_linear", _CODES["robertson"]: "robertson_linear",
                   _CODES["inverse-variance"]: "invvar_linear"}
#: the suffix of a one-pass kernel's radiance-only variant (no χ² statistic: its own
#: machine code, see mehs.synthesis._merge_fused.merge_chunk_poisson_linear_radiance)
_RADIANCE = "_radiance"
#: ... and of its variant with the χ² of binned bands (mehs.synthesis._merge_binned)
_BINNED = "_binned"


def _numba_kernel(kind: str | None, code: int):
    """The numba dispatcher of a merge (imports numba; says so if it will compile)."""
    from mehs.synthesis._numba_cache import notice_if_uncached
    from mehs.synthesis._numba_start import skip_scipy_linalg_import

    skip_scipy_linalg_import()
    if kind is not None:                 # a one-pass kernel: the one the native path stores
        from mehs.synthesis._native_specs import KERNELS

        kernel = KERNELS[kind].dispatcher()
    elif code == _CODES["poisson"]:
        from mehs.synthesis._merge_kernels import merge_chunk_poisson as kernel
    else:
        from mehs.synthesis._merge_kernels import merge_chunk as kernel
    # a first-ever run compiles for seconds: say so instead of looking hung (issue 16)
    notice_if_uncached(kernel, "the synthesis kernels")
    return kernel


def merge_bracket(stack: Sequence[np.ndarray], times_ms: Sequence[float], *,
                  method: str = "poisson", response: ResponseCurve | None = None,
                  darks: Sequence[np.ndarray | None] | None = None, bit_depth: int | None = None,
                  saturation: float | np.ndarray | None = None,
                  noise: NoiseModel | tuple[float, float] | None = None,
                  noise_floor: float | None = None, weighting: str = "hat",
                  calibration: float | np.ndarray = 1.0, chunk_lines: int = 128,
                  dark_mode: str = "auto", consistency: bool = True,
                  consistency_bins: int | str = "auto", clip_negative: bool = True,
                  source: Any = None) -> MergeResult:
    """Merge P exposures (shortest first or not) into a radiance cube.

    Parameters
    ----------
    stack
        P arrays (or :class:`~mehs.cube.SpectralCube`) ``(lines, samples, bands)``
        of raw DN (any integer or float dtype; memory maps are read chunk by
        chunk, never whole).
    times_ms
        Exposure times in ms, positive and distinct, one per exposure.
    method
        A key of :data:`MERGE_METHODS`.
    response
        A :class:`ResponseCurve`; None or a linear curve means a linear sensor.
    darks
        Per exposure ``(samples, bands)`` dark levels (or None = 0).
    bit_depth
        The raws' bit depth; default the response curve's, else 12. One that differs
        from the curve's raises :class:`InputError`.
    saturation
        Raw DN at or above which a sample is saturated: scalar or per band
        ``(bands,)``; default ``0.98·(2**bit_depth − 1)``.
    noise
        :class:`NoiseModel` or ``(gain, read_noise)``; default ``NoiseModel()``.
    noise_floor
        ``debevec`` only: samples with ``y ≤ noise_floor`` (DN) get zero weight;
        default the read noise.
    calibration
        Factor (scalar or per band) turning DN/ms into absolute radiance.
    dark_mode
        Non-linear curves only: ``"raw"`` subtracts the dark in DN before the
        curve (the curve was recovered on dark-subtracted levels);
        ``"linear"`` applies the curve to raw levels and subtracts the
        linearised dark, right when the black level is added before the
        non-linearity; ``"auto"`` follows ``response.parameters["levels"]``
        (``"raw"`` levels → ``"linear"``).
    clip_negative
        Clip negative estimates (noise around zero radiance) to 0 (default:
        radiance is non-negative, and renderers refuse negative light).
        ``False`` keeps the unbiased signed estimate, for noise studies.
    consistency
        Accumulate the per-pixel χ² consistency statistic (for ghost detection);
        ``False`` saves one pass over each row and leaves ``chi2`` at 0.
    consistency_bins
        Adjacent bands summed before the χ² statistic (1: per band). Bins of several
        bands detect more of the weakly moving pixels, whose change keeps its sign
        across neighbouring bands, and cost fewer divisions
        (:mod:`mehs.synthesis._merge_binned`); ``dof`` then counts bins. Implemented for
        the one-pass merges of a linear sensor — every method with a linear curve, the
        weighted ones with the hat weighting — at most 16 exposures; ``"auto"`` (default)
        takes :data:`AUTO_CONSISTENCY_BINS` there for cubes of at least
        :data:`AUTO_BINS_MIN_BANDS` bands and brackets of at most
        :data:`AUTO_BINS_MAX_EXPOSURES` (16) exposures, and 1 otherwise (few broad bands;
        a recovered curve or another weighting, whose kernels have no binned statistic).
        The radiance does not depend on it. ``info["consistency_bins"]`` records the
        choice.
    chunk_lines
        Most lines per kernel call. The kernel reads BIL inputs in place and writes
        straight into the output, so this bounds only the copy made for other
        layouts (or mixed dtypes); chunks run on numba's thread count
        (:func:`mehs.synthesis._ranges.thread_count`).
    """
    if method not in _CODES:
        raise InputError(f"unknown merge method {method!r}; use one of {sorted(_CODES)}")
    from mehs.cube import SpectralCube

    # np.asarray keeps memory maps as views (nothing is read here)
    arrays = [np.asarray(s.data if isinstance(s, SpectralCube) else s) for s in stack]
    P = len(arrays)
    if P < 2:
        raise InputError(f"a bracket needs at least 2 exposures, got {P}", source)
    shape = arrays[0].shape
    if len(shape) != 3:
        raise InputError(f"exposures must be (lines, samples, bands), got {shape}", source)
    for k, a in enumerate(arrays):
        if a.shape != shape:
            raise InputError(f"exposure {k} has shape {a.shape}, exposure 0 has {shape}", source)
    nl, ns, nb = shape
    t = np.asarray(times_ms, dtype=np.float64).reshape(-1)
    if t.size != P:
        raise InputError(f"{t.size} exposure times for {P} exposures", source)
    if not np.all(np.isfinite(t) & (t > 0)):
        raise InputError(f"exposure times must be positive, got {t.tolist()} ms", source)
    if np.unique(t).size != P:
        raise InputError(f"exposure times must be distinct, got {t.tolist()} ms", source)
    order = np.argsort(t, kind="stable")
    arrays = [arrays[i] for i in order]
    t = t[order]
    if bit_depth is None:
        bit_depth = response.bit_depth if response is not None else 12
    elif response is not None and response.bit_depth != int(bit_depth):
        # (the curve's depth used to win silently: 12-bit data merged through a 16-bit
        # curve took 0.98·65535 as saturation, and clipped samples as valid)
        raise InputError(f"the response curve is for {response.bit_depth}-bit data but "
                         f"bit_depth={bit_depth} was given", source)
    if response is None:
        response = ResponseCurve.linear(bit_depth)
    L = response.levels
    linear = response.is_linear
    glut = response.table(None if response.shared else nb).astype(np.float32)
    if not response.shared and glut.shape[0] != nb:
        raise InputError(f"response curve has {glut.shape[0]} bands, data has {nb}", source)
    elut = np.exp(glut.astype(np.float64)).astype(np.float32)
    wlut = weighting_table(weighting, L).astype(np.float32)
    # tables the kernel can compute instead of looking up (a gather per sample
    # does not vectorise): Debevec's hat and the linear curve's ln max(y, ½), both at the
    # fractional y = raw − dark (a rounded level put up to ±½ DN of the dark in every value)
    hat = bool(np.array_equal(wlut, weighting_table("hat", L).astype(np.float32)))
    lin_g = bool(np.all(glut == ResponseCurve.linear(int(bit_depth)).table()
                        .astype(np.float32)))

    if noise is None:
        noise = NoiseModel()
    elif not isinstance(noise, NoiseModel):
        noise = NoiseModel(*noise)
    # Debevec only (ln y needs y > 0): the linear estimators use every unsaturated
    # sample, since dropping the low ones by their own value biases them upward
    floor = noise.read_noise if noise_floor is None else float(noise_floor)
    if method == "debevec" and linear:
        floor = max(floor, 0.5)
    avar = noise.zero_signal_variance(t).astype(np.float32)

    sat = np.asarray(0.98 * (L - 1) if saturation is None else saturation, dtype=np.float32)
    if sat.ndim == 0:
        sat = np.full(nb, sat, dtype=np.float32)
    if sat.shape != (nb,):
        raise InputError(f"saturation must be a scalar or one value per band ({nb}), "
                         f"got shape {sat.shape}", source)
    if not np.all(np.isfinite(sat) & (sat > 0) & (sat <= L - 1)):
        # above the largest code nothing is ever "saturated": clipped samples would
        # count as measurements
        raise InputError(f"saturation must be in (0, {L - 1}] DN for {bit_depth}-bit data, got "
                         f"{float(sat.min()):g}..{float(sat.max()):g}", source)
    cal = np.asarray(calibration, dtype=np.float32)
    if cal.ndim == 0:
        cal = np.full(nb, cal, dtype=np.float32)
    if cal.shape != (nb,) or not np.all(np.isfinite(cal) & (cal > 0)):
        raise InputError("calibration must be a positive scalar or one positive value per band",
                         source)
    # the stored kernels take C-contiguous arrays only (a band subset's levels, sat[::2],
    # are a strided view)
    sat, cal = np.ascontiguousarray(sat), np.ascontiguousarray(cal)

    dk = np.zeros((P, ns, nb), dtype=np.float32)
    has_dark = np.zeros(P, dtype=bool)
    if darks is not None:
        darks = [darks[i] for i in order] if len(darks) == P else None
        if darks is None:
            raise InputError("one dark reference per exposure is needed", source)
        for j, d in enumerate(darks):
            if d is None:
                continue
            d = np.asarray(d, dtype=np.float32)
            if d.ndim == 3 and d.shape[0] >= 1:
                d = d.mean(axis=0)
            if d.shape != (ns, nb):
                raise InputError(f"dark reference {j} has shape {d.shape}, expected ({ns}, {nb})",
                                 source)
            if not np.all(np.isfinite(d)):
                raise InputError(f"dark reference {j} contains NaN or inf", source)
            dk[j] = d
            has_dark[j] = True

    if dark_mode == "auto":
        dark_mode = "linear" if response.parameters.get("levels") == "raw" else "raw"
    if dark_mode not in ("raw", "linear"):
        raise InputError(f"dark_mode must be 'auto', 'raw' or 'linear', got {dark_mode!r}")
    dark_after = (not linear) and dark_mode == "linear"
    if dark_after:
        # linearise the (fractional) dark levels through the curve, per band
        e = elut.astype(np.float64)
        zl = np.clip(dk, 0, L - 1)
        z0 = np.floor(zl).astype(np.intp)
        z1 = np.minimum(z0 + 1, L - 1)
        fr = zl - z0
        bidx = 0 if response.shared else np.arange(nb)[None, None, :]
        dk = ((1 - fr) * e[bidx, z0] + fr * e[bidx, z1]).astype(np.float32)
        # An exposure without a dark reference has nothing to subtract: exp g(0) is the
        # curve's extrapolated end, not a measured black level, and subtracting it
        # turned dark pixels negative (then clipped to exactly 0).
        dk[~has_dark] = 0.0

    # The kernel works band-outer / samples-inner (BIL): a BIL memmap is read
    # as is, other layouts are transposed chunk by chunk.
    views = [a.transpose(0, 2, 1) for a in arrays]
    dk_k = np.ascontiguousarray(dk.transpose(0, 2, 1))
    out = np.empty((nl, nb, ns), dtype=np.float32)
    chi2 = np.zeros((nl, ns), dtype=np.float32)
    dof = np.zeros((nl, ns), dtype=np.int32)
    snr = np.zeros((nl, ns), dtype=np.float32)
    nsat = np.zeros((nl, ns), dtype=np.int32)
    nvalid = np.zeros((nl, ns), dtype=np.int32)
    msum = np.zeros((nl, ns), dtype=np.float32)
    is_float = np.issubdtype(arrays[0].dtype, np.floating)
    same_dtype = len({a.dtype for a in arrays}) == 1
    # the kernels read native byte order: another one (a big-endian ENVI file) is
    # swapped chunk by chunk below
    kdtype = arrays[0].dtype.newbyteorder("=")
    swap = same_dtype and not arrays[0].dtype.isnative
    chunk_lines = max(1, int(chunk_lines))
    code = _CODES[method]
    # the one-pass kernels: a linear curve, the hat weighting computed (no tables)
    if code == _CODES["poisson"]:
        kind = "poisson_linear" if linear else None
    else:
        kind = (_WEIGHTED_KINDS[code] if linear and hat and lin_g else None)
    nbin = consistency_bins_value(consistency_bins, source)
    if nbin == "auto":
        nbin = auto_consistency_bins(kind is not None, nb, P)
    nbin = min(nbin, nb)      # (one bin of every band at most)
    if consistency and nbin > 1:
        if P > BINNED_MAX_EXPOSURES:
            # the kernel packs two exposure masks into one int32 per sample
            raise InputError(f"consistency_bins={nbin} takes at most {BINNED_MAX_EXPOSURES} "
                             f"exposures, got {P}; use consistency_bins=1", source)
        if kind is None:
            # (a weighted merge of a linear curve without its kernel: another weighting)
            why = (f"the {weighting!r} weighting (the binned {method} kernel computes the "
                   "hat)" if linear and lin_g and not hat else "a recovered response curve")
            raise InputError(f"consistency_bins={nbin} is implemented for the merges of a "
                             f"linear sensor only, not {why}; use consistency_bins=1", source)
        kind += _BINNED
    if kind is not None and not consistency:
        kind += _RADIANCE
    native = None
    if kind is not None and same_dtype:
        from mehs.synthesis import _native

        # machine code loaded without starting numba (None: numba's dispatcher below)
        native = _native.native_kernel(kind, kdtype, P)
    kernel = native or _numba_kernel(kind, code)
    t32 = t.astype(np.float32)
    gain, rel2 = float(noise.gain), float(noise.relative) ** 2

    fused_poisson = kind is not None and kind.startswith("poisson_linear")
    binned = kind is not None and kind.endswith(_BINNED)

    def work(l0: int, l1: int) -> None:
        parts = [np.asarray(v[l0:l1]) for v in views]
        if is_float:
            for j, part in enumerate(parts):
                if not np.all(np.isfinite(part)):
                    raise InputError(f"exposure {j} contains NaN or inf near lines {l0}..{l1 - 1}",
                                     source)
        if not same_dtype:
            parts = [p.astype(np.float32) for p in parts]
        elif swap:
            parts = [p.astype(kdtype) for p in parts]
        parts = tuple(p if p.flags.c_contiguous else np.ascontiguousarray(p) for p in parts)
        outs = (out[l0:l1], chi2[l0:l1], dof[l0:l1], snr[l0:l1], nsat[l0:l1],
                nvalid[l0:l1], msum[l0:l1])
        if binned:
            # the bin's running sums, per chunk (each thread its own)
            scratch = (tuple(np.empty(ns, np.float32) for _ in range(P)),
                       np.empty(ns, np.float32), np.empty(ns, np.int32))
            head = (parts, dk_k, sat, t32) + (() if fused_poisson else (L, np.float32(floor)))
            kernel(*head, gain, avar, rel2, cal, True, bool(clip_negative), nbin, *scratch,
                   *outs)
        elif fused_poisson:
            kernel(parts, dk_k, sat, t32, gain, avar, rel2, cal, bool(consistency),
                   bool(clip_negative), *outs)
        elif kind is not None:               # a weighted method's one-pass kernel
            kernel(parts, dk_k, sat, t32, L, np.float32(floor), gain, avar, rel2, cal,
                   bool(consistency), bool(clip_negative), *outs)
        elif code == _CODES["poisson"]:
            kernel(parts, dk_k, sat, t32, linear, dark_after, elut, L, gain, avar, rel2, cal,
                   bool(consistency), bool(clip_negative), *outs)
        else:
            kernel(parts, dk_k, sat, t32, linear, dark_after, glut, elut, wlut, hat, lin_g,
                   np.float32(floor), gain, avar, rel2, cal, code, bool(consistency),
                   bool(clip_negative), *outs)

    # chunks of lines, at most chunk_lines each, on numba's thread count (the kernels
    # release the GIL)
    from mehs.synthesis._ranges import run_ranges

    # A chunk that must be copied (a layout other than BIL, a reversed band axis, another
    # byte order, mixed dtypes) is copied whole, P exposures at once on every thread:
    # 128 lines of an FX10 (1024 samples × 224 bands) are 176 MB a chunk. Bounded by bytes,
    # the copies stay a few tens of MB whatever the sensor's width (BIL inputs are read in
    # place, and keep chunk_lines).
    in_place = same_dtype and not swap and all(
        v[:1].flags.c_contiguous for v in views) and not is_float
    if not in_place:
        row = ns * nb * P * max(4 if not same_dtype else arrays[0].dtype.itemsize, 1)
        chunk_lines = max(1, min(chunk_lines, COPY_CHUNK_BYTES // max(1, row)))
    run_ranges(nl, work, max_step=chunk_lines, name="mehs-merge")
    radiance = out.transpose(0, 2, 1)
    mask = np.zeros((nl, ns), dtype=np.uint8)
    mask[nsat > 0] |= MASK_SATURATED
    mask[nvalid == 0] |= MASK_INVALID
    if not np.any(nvalid > 0):
        what = ("saturated in every exposure" if np.all(nsat == nb)
                else "saturated or below the noise floor in every exposure")
        raise InputError(f"no usable sample in the bracket: every pixel is {what}", source)
    msum /= np.float32(nb)
    info = {"method": method, "times_ms": t.tolist(), "order": order.tolist(),
            "bit_depth": int(bit_depth), "response": response.method,
            "dark_mode": "linear" if dark_after else "raw",
            "dark_reference": [bool(h) for h in has_dark[np.argsort(order)]],
            "noise": {"gain": noise.gain, "read_noise": noise.read_noise,
                      "dark_current": noise.dark_current,
                      "relative": noise.relative, "floor": floor},
            "saturation_dn": sat.tolist() if np.unique(sat).size > 1 else float(sat[0]),
            "consistency_bins": nbin if consistency else None,
            "bands_saturated_in_all": int(nsat.sum()), "nvalid": nvalid}
    return MergeResult(radiance, (snr / nb).astype(np.float32), mask, chi2, dof, msum, info)


def warm_merge_kernel(stack: Sequence[np.ndarray], times_ms: Sequence[float], *,
                      method: str = "poisson", darks: Sequence[np.ndarray | None] | None = None,
                      bit_depth: int = 12, saturation: Any = None, linear: bool = True,
                      consistency: bool = True, consistency_bins: int | str = "auto"):
    """Start loading (or, on a first-ever run, compiling) the kernel a merge will need.

    Runs :func:`merge_bracket` on the first line of ``stack`` in a daemon thread and
    returns the thread: the kernel's specialisation depends only on the arrays' types
    (dtype, layout, read-only flag, number of exposures), the method, whether the
    response curve is linear (``linear=False``: any recovered curve, whose values do
    not matter here) and, for a linear one, whether the merge computes the ghost
    statistic (``consistency``), so that line gives the same one as the whole cube. Linking the
    stored kernel (:mod:`mehs.synthesis._native`, tens of ms), or importing numba and
    loading its cached kernel (0.3–0.6 s), or compiling (seconds), then overlaps the
    work a caller does before the merge (file checks, the linearity test); a later
    :func:`merge_bracket` waits for the build or numba's compiler lock if it has to.
    Any error is left to that later call.
    """
    import threading

    from mehs.cube import SpectralCube

    arrays = [np.asarray(s.data if isinstance(s, SpectralCube) else s) for s in stack]

    def run() -> None:
        try:
            curve = None if linear else ResponseCurve(
                np.log(np.maximum(np.arange(float(1 << bit_depth)), 0.5)), bit_depth,
                "warm-up")
            merge_bracket([a[:1] for a in arrays], times_ms, method=method, darks=darks,
                          bit_depth=bit_depth, saturation=saturation, response=curve,
                          consistency=consistency, consistency_bins=consistency_bins)
        except Exception:   # noqa: BLE001 - the real merge reports it
            pass

    t = threading.Thread(target=run, name="mehs-warm-merge", daemon=True)
    t.start()
    return t


def merge_Debevec1997(stack, times_ms, **kwargs) -> MergeResult:
    """Debevec & Malik's weighted log-domain mean (see module docstring)."""
    return merge_bracket(stack, times_ms, method="debevec", **kwargs)


def merge_Robertson2003(stack, times_ms, **kwargs) -> MergeResult:
    """Robertson et al.'s ``w·t²``-weighted linear mean."""
    return merge_bracket(stack, times_ms, method="robertson", **kwargs)


def merge_Hanji2020(stack, times_ms, **kwargs) -> MergeResult:
    """Hanji et al.'s Poisson (photon-noise ML) estimator ``Σ y / Σ t``."""
    return merge_bracket(stack, times_ms, method="poisson", **kwargs)


def merge_inverse_variance(stack, times_ms, **kwargs) -> MergeResult:
    """Inverse-variance weights from a gain / read-noise model (Granados et al. 2010)."""
    return merge_bracket(stack, times_ms, method="inverse-variance", **kwargs)


MERGE_METHODS = {
    "debevec": merge_Debevec1997,
    "robertson": merge_Robertson2003,
    "poisson": merge_Hanji2020,
    "inverse-variance": merge_inverse_variance,
}
