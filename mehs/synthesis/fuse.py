"""Bracket → HDR radiance cube: response recovery, merge, ghost handling, outputs.

:func:`fuse_bracket` is the library form of ``mehs fuse``; :func:`write_fusion`
writes its result (ENVI float32 radiance with wavelengths, mask and
confidence, the response curve and a JSON summary).
"""

from __future__ import annotations

import functools
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.merge import (MASK_GHOST, MASK_INVALID, MASK_SATURATED, MERGE_METHODS,
                                  NoiseModel, merge_bracket, warm_merge_kernel)
from mehs.synthesis.merge_types import (BINNED_MAX_EXPOSURES, GHOST_BINS_NAME,
                                         consistency_bins_value, refuse_bins_for_curve)
from mehs.synthesis.fuse_response import (  # noqa: F401 - re-exported (library API)
    LINEARITY_TOLERANCE, ResponseUndeterminedWarning, check_recovered_response, choose_response,
    recover_response)
from mehs.synthesis.response import ResponseCurve

@dataclass
class FusionResult:
    """Output of :func:`fuse_bracket`.

    Attributes
    ----------
    radiance
        float32 cube ``(lines, samples, bands)``, units ``"DN/ms"`` (relative) or
        ``"radiance"`` after calibration.
    confidence
        float32 ``(lines, samples)``: expected SNR of the merged value, mean over bands.
    mask
        uint8 ``(lines, samples)``: bit 1 saturated in every exposure (some band) — or,
        de-ghosted, in the reference exposure (a lower bound) — bit 2 ghost, bit 4 no
        usable signal.
    response
        The curve used.
    summary
        JSON-able figures: dynamic range (stops), saturated / ghost / invalid
        fractions, exposure times and ratios, method, noise model, timings.
    ghost_score
        float32 ``(lines, samples)`` normalised χ²/dof, or None with ``ghosts="off"``.
    """

    radiance: SpectralCube
    confidence: np.ndarray
    mask: np.ndarray
    response: ResponseCurve
    summary: dict[str, Any]
    ghost_score: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)


def noise_from_bracket(bracket: Bracket) -> NoiseModel:
    """The noise model of the recorded sensor (``scene.json`` device.sensor), else the default.

    Only a fallback for :func:`estimate_noise`, which measures the noise from
    the data (the recorded read noise misses quantisation, the dark
    reference's error and dark-current shot noise).
    """
    s = bracket.sensor
    try:
        gain = float(s["gain_dn_per_e"])
        read = float(s.get("read_noise_e", 0.0)) * gain
        dc = float(s.get("dark_current_e_per_ms", 0.0)) * gain
        return NoiseModel(gain=gain, read_noise=float(np.hypot(max(read, 0.5), np.sqrt(1 / 12))),
                          relative=0.0, dark_current=dc, source="recorded sensor")
    except (KeyError, TypeError, ValueError):
        return NoiseModel(source="default")


def _dark_mode(curve: ResponseCurve) -> str:
    return "linear" if (not curve.is_linear and curve.parameters.get("levels") == "raw") else "raw"


def estimate_noise(bracket: Bracket, curve: ResponseCurve, saturation: np.ndarray, *,
                   probe=None) -> tuple[NoiseModel, dict[str, Any]]:
    """The bracket's noise model measured from its own exposures (photon transfer).

    See :mod:`mehs.synthesis.noise`. Falls back to the recorded sensor (or the
    default model) when the bracket has too little usable signal to measure
    it; the returned dict says which was used and why.
    """
    from mehs.synthesis.noise import dark_current_from_darks, estimate_noise_PTC, probe_bracket

    try:
        probe = probe if probe is not None else probe_bracket(bracket, saturation)
        lin = _lineariser(curve, _dark_mode(curve), bracket.bit_depth,
                          [d is not None for d in bracket.darks])
        darks = bracket.darks
        if not curve.is_linear and all(d is not None for d in darks):
            # the dark's growth in linearised DN (through the curve, as the merge does)
            e = np.exp(curve.table())
            darks = [_exp_curve_at(e, curve.shared, np.asarray(d, dtype=np.float64))
                     for d in darks]
        dc = dark_current_from_darks(darks, bracket.times_ms)
        model, diag = estimate_noise_PTC(probe, lin, dark_current=dc, linear=curve.is_linear,
                                         key="linear" if curve.is_linear else None)
        return model, diag
    except InputError as exc:
        fb = noise_from_bracket(bracket)
        return fb, {"fallback": f"{fb.source} ({exc.problem})"}


def _after_file_check(fuse):
    """Run ``fuse(bracket, ...)``, then wait for the bracket's deferred file check
    (:meth:`Bracket.check_files`): no result from a file that fails it, and its error
    rather than the one a damaged file may have caused."""
    @functools.wraps(fuse)
    def checked(bracket, *args, **kwargs):
        try:
            result = fuse(bracket, *args, **kwargs)
        except Exception:
            if isinstance(bracket, Bracket):
                bracket.check_files()
            raise
        if isinstance(bracket, Bracket):
            bracket.check_files()
        return result
    return checked


@_after_file_check
def fuse_bracket(bracket: Bracket, *, method: str = "poisson", response: Any = "auto",
                 ghosts: str = "detect", smoothness: float | None = None,
                 samples: int | None = None,
                 seed: int = 0, shared_response: bool = True,
                 noise: NoiseModel | tuple[float, float] | str | None = "auto",
                 saturation: float | np.ndarray | None = None,
                 calibration: float | np.ndarray | None = None, ghost_alpha: float = 1e-4,
                 reference: int | str = "auto", chunk_lines: int = 128,
                 check_response: bool = True, clip_negative: bool = False,
                 ghost_bins: int | str = "auto") -> FusionResult:
    """Fuse a bracket into an HDR radiance cube.

    Parameters
    ----------
    method
        Merge estimator, a key of :data:`mehs.synthesis.merge.MERGE_METHODS`.
    response
        ``"auto"`` (the linear curve when the exposures agree with it — the ratio
        ``Σy_k/(r·Σy_j)`` of consecutive exposures stays within 2 % of 1 at (75 % of)
        the well-exposed signal levels, see :func:`mehs.synthesis.noise.linearity_PTC` —
        else a Debevec curve recovered on raw levels), ``"linear"``,
        ``"debevec"`` (always recover), a :class:`ResponseCurve`, or the path of
        a saved curve (JSON).
    ghosts
        ``"detect"`` (flag, mask bit 2), ``"deghost"`` (flag and take ghost pixels
        from one reference exposure), or ``"off"``.
    noise
        ``"auto"`` (default, also ``None``): measured from the bracket by photon
        transfer across exposures (:func:`estimate_noise`; falls back to the
        recorded sensor); ``"recorded"``: ``scene.json``'s sensor; or a
        :class:`NoiseModel` / ``(gain, read_noise)``.
    saturation
        Raw DN at or above which a sample is saturated (scalar or per band). None: 0.98·(L−1),
        lower in the bands where the longest exposure shows the sensor clipping below it
        (:func:`mehs.synthesis.saturation.detect_saturation`; ``summary["saturation_detected"]``).
    calibration
        A :class:`mehs.calibration.Calibration` (or the path of its file): the
        merged DN/ms are divided by its per-column, per-band responsivity and
        the cube's unit becomes the calibration's (W sr-1 m-2 nm-1 or relative
        radiance); a calibration of another camera, band set or binning is refused.
        A number or per-band array is a plain factor from DN/ms to radiance.
    clip_negative
        Clip negative estimates (noise around zero radiance) to 0. Off by default: the
        signed estimate is unbiased, while clipping raised the darkest pixels' mean
        (×1.43 at 2–4 DN of signal; +2 % in a scene's darkest decile, more after band
        averaging). The RGB step clips, as the paper does, and HS environment maps clip
        on loading; summary ``negative_fraction`` counts the negative samples.
    ghost_bins
        Adjacent bands summed per term of the merge's χ² ghost statistic
        (``consistency_bins`` of :func:`~mehs.synthesis.merge.merge_bracket`): ``"auto"``
        (default: 4 for a linear sensor's cube of ≥ 100 bands and ≤ 16 exposures, else 1)
        or a whole number; more than 1 only for a linear sensor (every merge method) and
        at most 16 exposures (else an ``InputError`` before the merge; a curve that
        ``response="auto"`` recovers is refused right after it is chosen).
        ``summary["ghost_chi2_bins"]`` records what was used.
    check_response
        After recovering a curve, run the self-consistency check of
        :mod:`mehs.synthesis.response_check` (three more solves): its figures go
        to ``summary["response"]["check"]``; an undetermined curve adds a
        ``summary["warnings"]`` entry and a :class:`ResponseUndeterminedWarning`.

    A bracket loaded with ``load_bracket(..., defer_verify=True)`` is fused while
    its files are hashed; the result is returned only once they matched their
    record (else the :class:`~mehs.errors.FormatError` naming the file is raised).
    """
    if method not in MERGE_METHODS:
        raise InputError(f"unknown merge method {method!r}; use one of {sorted(MERGE_METHODS)}")
    if ghosts not in ("detect", "deghost", "off"):
        raise InputError(f"ghosts must be 'detect', 'deghost' or 'off', got {ghosts!r}")
    # these are used only on some paths (response recovery, ghosts found); checked
    # here so a bad value is an error on every run, not a silently ignored option
    # None: chosen from the data (fuse_response.recover_response)
    if smoothness is not None and not (np.isfinite(smoothness) and smoothness > 0):
        # levels no sample weights are tied to the curve by the smoothness term alone
        raise InputError(f"smoothness (lambda) must be finite and > 0, got {smoothness}")
    if samples is not None and int(samples) < 1:
        raise InputError(f"samples must be at least 1, got {samples}")
    ghost_bins = consistency_bins_value(ghost_bins, what=GHOST_BINS_NAME)
    binned = ghost_bins not in ("auto", 1) and ghosts != "off"
    # refused before the response work where it can be known, not at the merge
    n_exp = len(bracket.times_ms)
    if binned and n_exp > BINNED_MAX_EXPOSURES:
        raise InputError(f"{GHOST_BINS_NAME} = {ghost_bins} takes at most "
                         f"{BINNED_MAX_EXPOSURES} exposures, this bracket has {n_exp}; use 1 "
                         "or auto", bracket.source)
    if binned and isinstance(response, str) and response == "debevec":
        refuse_bins_for_curve(ghost_bins, "the response asked for", "debevec", bracket.source)
    if reference != "auto" and not (isinstance(reference, (int, np.integer))
                                    and 0 <= reference < n_exp):
        raise InputError(f"reference must be 'auto' or an exposure index 0..{n_exp - 1}, "
                         f"got {reference!r}", bracket.source)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    nl, ns, nb = bracket.shape
    L = 1 << bracket.bit_depth
    sat_found = None
    if saturation is None:
        # a sensor that clips below 0.98·(L − 1) (its full well, an ADC saturating low)
        # would have its plateau merged as measurements: found from the longest exposure
        from mehs.synthesis.saturation import detect_saturation, notice

        sat, sat_found = detect_saturation(bracket, 0.98 * (L - 1))
        notice(sat_found, bracket.source)
    else:
        sat = np.asarray(saturation, dtype=np.float64)
    try:
        sat = np.broadcast_to(sat, (nb,)).astype(np.float32)
    except ValueError:
        raise InputError(f"saturation must be one level or one per band ({nb}), got shape "
                         f"{np.shape(sat)}", bracket.source) from None
    if str(response) == "auto" or noise is None or (isinstance(noise, str) and noise == "auto"):
        from mehs.synthesis._ptc_groups import build_kernels_in_background

        # a first-ever run: the photon-transfer kernels compile in child processes
        # while the merge kernel compiles here
        build_kernels_in_background()
    ghost_statistic = ghosts != "off"    # the merge's χ²: its own kernel, warmed here
    # numba's import and kernel load (or first-ever compile) overlap the checks below
    warm_merge_kernel([e.data for e in bracket.exposures], bracket.times_ms, method=method,
                      darks=bracket.darks, bit_depth=bracket.bit_depth, saturation=sat,
                      consistency=ghost_statistic, consistency_bins=ghost_bins)
    curve, auto_info, probe = choose_response(
        bracket, response, method=method, saturation=sat, smoothness=smoothness,
        samples=samples, seed=seed, shared=shared_response, check=check_response)
    if curve.bit_depth != bracket.bit_depth:
        raise InputError(f"response curve is {curve.bit_depth}-bit, the bracket "
                         f"{bracket.bit_depth}-bit", bracket.source)
    _check_curve_bands(curve, bracket)
    timings["response_s"] = time.perf_counter() - t0

    noise_info: dict[str, Any] = {}
    t_noise = time.perf_counter()
    if noise is None or (isinstance(noise, str) and noise == "auto"):
        noise, noise_info = estimate_noise(bracket, curve, sat, probe=probe)
    elif isinstance(noise, str) and noise == "recorded":
        noise = noise_from_bracket(bracket)
    elif isinstance(noise, str):
        raise InputError(f"noise must be 'auto', 'recorded', a NoiseModel or (gain, read_noise), "
                         f"got {noise!r}")
    elif not isinstance(noise, NoiseModel):
        noise = NoiseModel(*noise)
    timings["noise_s"] = time.perf_counter() - t_noise
    radiometric = None
    if isinstance(calibration, (str, Path)):
        from mehs.calibration import Calibration

        calibration = Calibration.load(calibration)
    if calibration is not None and not np.isscalar(calibration) and hasattr(calibration, "apply"):
        from mehs.calibration.calibrate import bracket_camera_id

        radiometric = calibration
        radiometric.check_compatible(bracket.wavelengths, bracket.shape[1], camera_id=bracket_camera_id(bracket),
                                     binning=bracket.exposures[0].binning, source=bracket.source,
                                     bit_depth=bracket.bit_depth, response=curve)
        calibration = None
    cal = 1.0 if calibration is None else calibration
    if binned and not curve.is_linear:
        refuse_bins_for_curve(ghost_bins, "this bracket's response", curve.method,
                              bracket.source)
    t1 = time.perf_counter()
    mr = merge_bracket([e.data for e in bracket.exposures], bracket.times_ms, method=method,
                       response=curve, darks=bracket.darks, bit_depth=bracket.bit_depth,
                       saturation=sat, noise=noise, calibration=cal, chunk_lines=chunk_lines,
                       consistency=ghost_statistic, consistency_bins=ghost_bins,
                       clip_negative=clip_negative, source=bracket.source)
    timings["merge_s"] = time.perf_counter() - t1
    mask = mr.mask
    radiance = mr.radiance
    ghost_score = None
    ghost_fraction = None      # not tested (ghosts="off"): unknown, not zero
    ref_used = None
    ref_bound = None           # ghosts="deghost": pixels left at the reference's lower bound
    gres = None
    if ghost_statistic:
        from mehs.synthesis.ghost import deghost_from_reference, detect_ghosts

        t2 = time.perf_counter()
        # a recovered curve errs by different amounts at different levels (most
        # near black): its χ² scale is taken per signal level; a linear sensor's
        # measured noise model fits at every level, one scale for the frame
        gres = detect_ghosts(mr.chi2, mr.dof, alpha=ghost_alpha,
                             scale="auto" if curve.is_linear else "level",
                             level=mr.mean_radiance)
        ghost_score = gres.score
        ghost_fraction = gres.fraction
        mask[gres.mask] |= MASK_GHOST
        if ghosts == "deghost" and gres.mask.any():
            lin = _lineariser(curve, mr.info["dark_mode"], bracket.bit_depth,
                              [d is not None for d in bracket.darks])
            ref_bound = np.zeros(mask.shape, dtype=bool)
            ref_used = deghost_from_reference(
                radiance, gres.mask, [e.data for e in bracket.exposures], bracket.darks,
                bracket.times_ms, linearise=lin, saturation=sat, floor=mr.info["noise"]["floor"],
                calibration=np.broadcast_to(np.asarray(cal, dtype=np.float64), (nb,)),
                reference=reference, clip_negative=clip_negative, lower_bound=ref_bound)
            # saturated in the reference: a lower bound of what it saw (a shorter exposure
            # saw another instant), flagged like a band saturated in every exposure
            mask[ref_bound] |= MASK_SATURATED
        timings["ghosts_s"] = time.perf_counter() - t2

    e0 = bracket.exposures[0]
    wavelengths, fwhm = bracket.wavelengths, e0.fwhm
    if radiometric is not None:
        # after the merge and any deghosting: per column and band, DN/ms → radiance
        # (only the bands the calibration covers remain)
        radiance = radiometric.apply(radiance, out=radiance if radiometric.complete else None)
        wavelengths = radiometric.calibrated_wavelengths
        if fwhm is not None and not radiometric.complete:
            fwhm = np.asarray(fwhm)[radiometric.bands]
        units = radiometric.unit
    else:
        units = "DN/ms" if calibration is None else "radiance"
    cube = SpectralCube(radiance, wavelengths, fwhm=fwhm, units=units,
                        integration_time_ms=None, acquisition_date=e0.acquisition_date,
                        binning=e0.binning, dark_subtracted=True, source=bracket.source,
                        default_bands=(e0.default_bands if radiometric is None
                                       or radiometric.complete else None),
                        metadata={"mehs merge method": method,
                                  "mehs response": curve.method,
                                  "mehs exposure times ms": [float(t) for t in bracket.times_ms]})
    summary = _summary(mr, mask, bracket, curve, method, ghosts, ghost_fraction, gres, noise,
                       calibration, ref_used, auto_info)
    summary["ghost_reference_saturated_fraction"] = (
        None if ghosts != "deghost" or gres is None
        else 0.0 if ref_bound is None else float(ref_bound.mean()))
    summary["units"] = units
    summary["saturation_detected"] = sat_found
    summary["negative_fraction"] = _negative_fraction(radiance)
    if radiometric is not None:
        summary["calibration"] = radiometric.summary()
        summary["shape"] = list(radiance.shape)
        summary["wavelength_range_nm"] = [float(wavelengths[0]), float(wavelengths[-1])]
        summary["dynamic_range_definition"] += " (in DN/ms, before radiometric calibration)"
    summary["noise"].update(noise_info)
    chk = auto_info.get("check")
    summary["response_undetermined"] = bool(chk is not None and not chk.get("determined", True))
    if summary["response_undetermined"]:
        why = (chk["reason"] if chk.get("reason") else
               f"median uncertainty {chk['median']:.1%} of the linearised signal "
               f"(> {chk['threshold']:.0%})" if chk.get("median") is not None
               else "not checkable")
        from mehs.synthesis.response_check import ADVICE

        if auto_info.get("assumed_linear"):
            msg = (f"response curve undetermined by this bracket: {auto_info['assumed_linear']} "
                   f"({why}); merged with the linear curve, which may be wrong — {ADVICE}, or "
                   "pass --response linear for a sensor known to be linear")
        else:
            msg = (f"response curve undetermined by this bracket: {why}; the radiance is "
                   f"unreliable — {ADVICE}")
        summary.setdefault("warnings", []).append(msg)
        warnings.warn(ResponseUndeterminedWarning(msg), stacklevel=3)   # past _after_file_check
    timings["total_s"] = time.perf_counter() - t0
    summary["timings"] = timings
    return FusionResult(cube, mr.confidence, mask, curve, summary, ghost_score,
                        extras={"chi2": mr.chi2, "dof": mr.dof})


def _lineariser(curve: ResponseCurve, dark_mode: str, bit_depth: int,
                has_dark: list[bool] | None = None):
    """The merge's own raw → dark-subtracted linear DN mapping, for numpy arrays (n, bands).

    ``has_dark[j]`` False: exposure ``j`` has no dark reference, so nothing is
    subtracted after linearisation (as :func:`merge_bracket` does). Levels are clamped
    to the curve's table, whose size is ``2**bit_depth`` (the callers' brackets are
    checked against their curve).
    """
    if curve.is_linear:
        return lambda raw, dark, j: raw - dark
    e = np.exp(curve.table())

    def lut(z):
        return _exp_curve_at(e, curve.shared, np.rint(z))

    if dark_mode == "linear":
        def lin(raw, dark, j):
            if has_dark is not None and not has_dark[j]:
                return lut(raw)
            return lut(raw) - _exp_curve_at(e, curve.shared, np.broadcast_to(dark, raw.shape))
        return lin
    return lambda raw, dark, j: lut(raw - dark)


def _exp_curve_at(e: np.ndarray, shared: bool, zf: np.ndarray) -> np.ndarray:
    """``exp g`` (the table ``e``, ``(1 or bands, levels)``) at levels ``zf`` ``(..., bands)``,
    interpolated between integer levels and clamped to the table: each band through its
    own curve unless ``shared``."""
    L = e.shape[-1]
    zf = np.clip(zf, 0, L - 1)
    z0 = np.floor(zf).astype(np.intp)
    z1 = np.minimum(z0 + 1, L - 1)
    fr = zf - z0
    if shared:
        return (1 - fr) * e[0][z0] + fr * e[0][z1]
    b = np.arange(zf.shape[-1])
    return (1 - fr) * e[b, z0] + fr * e[b, z1]


def dynamic_range_stops(mean_radiance: np.ndarray, mask: np.ndarray, *,
                        percentiles: tuple[float, float] = (0.1, 99.9)) -> tuple[float | None, float | None]:
    """The scene's dynamic range in stops: ``log2(P_hi / P_lo)`` of the per-pixel band-mean radiance.

    Counted: every pixel with a positive estimate except ghosts (bit 2) and pixels
    with no usable signal (bit 4). Pixels saturated in some band in every
    exposure (bit 1: a lamp) count with their lower bound, so the figure is a
    lower bound of the lamp-to-shadow range rather than blind to the lamp.
    Percentiles 0.1 / 99.9 keep a handful of noisy pixels from setting it;
    the second value uses the extreme pixels.
    """
    m = mean_radiance
    use = ((mask & (MASK_GHOST | MASK_INVALID)) == 0) & (m > 0) & np.isfinite(m)
    if use.sum() < 2:
        return None, None
    v = m[use]
    lo, hi = np.percentile(v, list(percentiles))
    dr = float(np.log2(hi / lo)) if lo > 0 else None
    return dr, float(np.log2(v.max() / v.min()))


def _check_curve_bands(curve, bracket) -> None:
    """A per-band curve of another band set (same count, other centres: another binning or
    spectral calibration) would linearise each band with another band's curve."""
    from mehs.bandmeta import check_same_bands

    if curve.shared or curve.wavelengths is None or bracket.wavelengths is None:
        return
    check_same_bands(curve.wavelengths, bracket.wavelengths, "the per-band response curve",
                     "the bracket", bracket.source)


def _negative_fraction(radiance: np.ndarray) -> float:
    # by line: the cube may be as large as the bracket
    n = sum(int(np.count_nonzero(radiance[i] < 0)) for i in range(radiance.shape[0]))
    return n / max(1, radiance.size)


def _summary(mr, mask, bracket, curve, method, ghosts, ghost_fraction, gres, noise,
             calibration, ref_used, auto_info) -> dict[str, Any]:
    dr, dr_max = dynamic_range_stops(mr.mean_radiance, mask)
    t = bracket.times_ms
    return {
        "format": "mehs-fusion/1",
        "source": None if bracket.source is None else str(bracket.source),
        "shape": list(bracket.shape),
        "wavelength_range_nm": [float(bracket.wavelengths[0]), float(bracket.wavelengths[-1])],
        "method": method,
        "response": {"method": curve.method, "shared": curve.shared,
                     "smoothness": curve.smoothness, "dark_mode": mr.info["dark_mode"],
                     **auto_info},
        "times_ms": t.tolist(),
        "exposure_ratios": (t / t[0]).tolist(),
        "dynamic_range_stops": dr,
        "dynamic_range_stops_max": dr_max,
        "dynamic_range_definition": "log2(P99.9/P0.1) of per-pixel band-mean radiance over "
                                    "non-ghost pixels with signal; saturated pixels count "
                                    "with their lower bound",
        "saturated_fraction": float(np.mean(mask & 1 > 0)),
        "ghost_fraction": None if ghost_fraction is None else float(ghost_fraction),
        "invalid_fraction": float(np.mean(mask & 4 > 0)),
        "valid_fraction": float(np.mean(mask == 0)),
        "ghosts": ghosts,
        "ghost_chi2_scale": None if gres is None else gres.scale,
        # bands summed per bin of the χ² statistic (None: not computed)
        "ghost_chi2_bins": mr.info.get("consistency_bins"),
        # the χ² over its expectation under the noise model (below 1: the model overstates
        # the noise; kept for the record, never divided out — see mehs.synthesis.ghost)
        "ghost_chi2_fit": (None if gres is None or not np.isfinite(gres.fit)
                           else float(gres.fit)),
        "ghost_reference_exposure": ref_used,
        "noise": noise.as_dict(),
        "calibration": None if calibration is None else np.asarray(calibration).tolist(),
        "units": "DN/ms (uncalibrated)" if calibration is None else "radiance",
        "mean_confidence": float(mr.confidence.mean()),
        "bit_depth": bracket.bit_depth,
    }


# written by its own module (re-exported: the library API has it here)
from mehs.synthesis.fuse_write import write_fusion  # noqa: E402,F401
