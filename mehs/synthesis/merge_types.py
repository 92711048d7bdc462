"""What a merge takes and gives besides the raws: the noise model and the result.

Kept apart from :mod:`mehs.synthesis.merge` (which re-exports them) so that the merge's
own module holds its algorithm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NoReturn

import numpy as np

from mehs.errors import InputError

#: mask bits shared with the dataset format
MASK_SATURATED, MASK_GHOST, MASK_INVALID = 1, 2, 4

#: Most exposures of a binned χ² ghost statistic (its kernel keeps two bit masks of the
#: exposures in an int32).
BINNED_MAX_EXPOSURES = 16

#: the bands per bin of the χ² ghost statistic of ``consistency_bins="auto"`` where the
#: merge has a binned statistic (benchmarks/bench_ghost_bands.py: bins of 4 flag 99.8 % of
#: the pixels whose change is 10–30σ over all bands, the per-band statistic 93.5 %; ~15 %
#: less merge time, benchmarks/RESULTS.md "Issue 16, session 33")
AUTO_CONSISTENCY_BINS = 4
#: ... for cubes of at least this many bands: a dense spectrum, whose neighbouring bands a
#: moving object changes alike (a Specim IQ's 204 bands are 3 nm apart, an FX10's 224
#: 2.7 nm); a few broad bands (31 at 10 nm, three colours) keep one band per bin, as a
#: change may flip its sign between them
AUTO_BINS_MIN_BANDS = 100
#: ... of brackets of at most this many exposures: all the binned kernels take. Their
#: stored (mehs cache) kernels are vectorised up to 16 exposures, as fast per exposure as
#: for 3 (mehs.synthesis._native_child.llvm_options; session 35 had held "auto" to 3
#: exposures, beyond which they were scalar). The choice does not depend on where the
#: kernel comes from, at a price where numba's own build runs (no mehs cache folder, a
#: platform where stored kernels cannot be linked): there the binned kernels are scalar
#: from 4 exposures, the per-band ones but Debevec's from 6, so brackets of 4 or 5
#: exposures merge ~5× slower than per band (review of session 36).
AUTO_BINS_MAX_EXPOSURES = BINNED_MAX_EXPOSURES


def auto_consistency_bins(binned_kernel: bool, bands: int, exposures: int) -> int:
    """The bin width ``consistency_bins="auto"`` takes: :data:`AUTO_CONSISTENCY_BINS` for
    a merge with a binned statistic (``binned_kernel``: a linear sensor's one-pass merge)
    of at least :data:`AUTO_BINS_MIN_BANDS` bands and at most
    :data:`AUTO_BINS_MAX_EXPOSURES` exposures, else 1."""
    return (AUTO_CONSISTENCY_BINS if binned_kernel and bands >= AUTO_BINS_MIN_BANDS
            and exposures <= AUTO_BINS_MAX_EXPOSURES else 1)


#: How the fusion and the build name the bin width in their messages: the library's
#: argument and the command-line option.
GHOST_BINS_NAME = "ghost_bins (--ghost-bins)"


def refuse_bins_for_curve(ghost_bins, whose: str, curve: str, source=None) -> NoReturn:
    """Raise the ``InputError`` of a bin width > 1 with a non-linear response curve:
    ``whose`` names it ("this bracket's response"), ``curve`` is its method.

    Said alike wherever it is known before the merge, whose own refusal would come only
    after the response and noise work: :func:`mehs.synthesis.fuse.fuse_bracket` for
    ``response="debevec"`` and again once ``auto`` has chosen a curve,
    :func:`mehs.dataset.build.build_dataset` for a curve file before any scene.
    """
    raise InputError(f"{GHOST_BINS_NAME} = {ghost_bins} needs a linear sensor, and {whose} "
                     f"is {curve!r} (not linear): the merge of a non-linear curve has no "
                     "binned statistic; use 1 or auto", source)


@dataclass(frozen=True)
class NoiseModel:
    """Noise of a dark-subtracted, linearised sample ``y`` (DN) of an exposure of ``t`` ms.

    ``var(y) = gain·y + read_noise² + gain·dark_current·t + (relative·y)²``

    ``gain`` is in DN per electron (shot noise), ``read_noise`` in DN (one
    sigma at zero signal, after dark subtraction: read noise, quantisation and
    the dark reference's own error), ``dark_current`` in DN/ms (its electrons
    add shot noise although the dark subtraction removes their mean),
    ``relative`` a systematic relative error between exposures (response-curve
    error; 0 for a linear sensor, whose flat-field error is the same in every
    exposure and cancels in the consistency test). :func:`mehs.synthesis.noise.estimate_noise_PTC`
    measures all of them from a bracket.
    """

    gain: float = 1.0
    read_noise: float = 2.0
    relative: float = 0.01
    dark_current: float = 0.0
    source: str = "default"

    def __post_init__(self) -> None:
        for name in ("gain", "read_noise", "relative", "dark_current"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"noise model {name} must be finite and ≥ 0, got {v}")
        if self.gain == 0 and self.read_noise == 0:
            raise InputError("noise model needs gain > 0 or read_noise > 0")

    def zero_signal_variance(self, times_ms) -> np.ndarray:
        """float64 ``(P,)``: ``var(y)`` at zero signal for each exposure time."""
        t = np.asarray(times_ms, dtype=np.float64)
        return self.read_noise ** 2 + self.gain * self.dark_current * t

    def as_dict(self) -> dict:
        return {"gain_dn_per_e": self.gain, "read_noise_dn": self.read_noise,
                "dark_current_dn_per_ms": self.dark_current, "relative": self.relative,
                "source": self.source}


@dataclass
class MergeResult:
    """What :func:`merge_bracket` returns.

    Attributes
    ----------
    radiance
        float32 ``(lines, samples, bands)`` (possibly a transposed view of a
        band-interleaved buffer).
    confidence
        float32 ``(lines, samples)``: expected signal-to-noise ratio of the
        merged radiance (noise model), averaged over bands; 0 where no sample was usable.
    mask
        uint8 ``(lines, samples)``: bit 1 some band saturated in every exposure,
        bit 4 no usable sample in any band.
    chi2, dof
        float32 / int32 ``(lines, samples)``: Σ over bands and usable exposures of
        the squared normalised residuals ``(y_j/t_j − X)²/var_j`` and its degrees
        of freedom (Σ (usable − 1)) — over bins of adjacent bands, their levels summed,
        with ``consistency_bins`` > 1 (``info["consistency_bins"]``); input of
        :func:`mehs.synthesis.ghost.detect_ghosts`.
    mean_radiance
        float32 ``(lines, samples)``: mean over bands of the radiance.
    """

    radiance: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    mean_radiance: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def consistency_bins_value(value: Any, source: Any = None,
                           what: str = "consistency_bins") -> int | str:
    """``"auto"`` or a whole number of bands ≥ 1 per bin of the χ² ghost statistic (an
    int, or its decimal string as a command line gives it); anything else is an
    :class:`~mehs.errors.InputError` naming ``what``."""
    if isinstance(value, str):
        text = value.strip().lower()
        if text == "auto":
            return "auto"
        # ASCII digits only (str.isdecimal takes "٤" and "４"), and few enough for int()
        if text.isascii() and text.isdigit() and len(text) <= 9:
            value = int(text)
    if (isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
            and value >= 1):
        return int(value)
    raise InputError(f"{what} must be 'auto' or a whole number of bands ≥ 1, got {value!r}",
                     source)
