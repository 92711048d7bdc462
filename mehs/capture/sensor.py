"""A physically based line-scan sensor model.

For one spatial line (samples × bands) exposed for ``t`` ms to radiance ``L``::

    λ  = L · qe · radiance_to_e_per_ms · t + dark_current_e_per_ms · t      [electrons]
    e  = min(Poisson(λ), full_well_e) + read_noise_e · N(0, 1)              (shot, well, read)
    x  = gain_dn_per_e · e + black_level_dn + fpn[sample, band]            [linear DN]
    z  = clip(round(R(max(x, 0))), 0, 2**bit_depth − 1)                     (response, ADC)

The order is the camera's (EMVA 1288's linear model, with the well as a charge
limit): photo- and dark electrons (Poisson) collect in the pixel up to its full
well; read noise joins at read-out, so a pixel clipped by its well still varies
by ``gain·read_noise_e`` DN about ``gain·full_well_e + black + fpn``; the ADC then
clips at ``0`` and ``2**bit_depth − 1``, whichever of the two limits comes first
(at the defaults, 20 000 e⁻ × 0.25 DN/e⁻ + 32 = 5032 DN: the ADC's 4095).

``R`` is the camera response on the DN scale (``R(0) = 0``, ``R(full) = full``):
linear, a mild gamma ``full·(x/full)**gamma``, an S-curve
``full·(u − a·sin(2πu)/2π)`` with ``u = x/full``, or any monotonic callable.
Column fixed-pattern noise ``fpn`` is an offset fixed per (sample, band), drawn
from the sensor seed. Away from the well, shot and read noise are drawn together
as one normal ``λ + √(λ + σ_read²)·N`` (same mean and variance as Poisson +
Gaussian); the shot noise is drawn exactly from a Poisson law wherever the
sum's skewness ``λ / (λ + σ_read²)^1.5`` exceeds :data:`MAX_NORMAL_SKEW` (it
peaks at ``0.385/σ_read`` for ``λ = 2σ_read²``, so never with ≥ 8 e⁻ read
noise; with none, for ``λ < 400``). Within 6 σ of the well the shot noise is
drawn apart from the read noise, to be clipped alone. This keeps a
512×512×204×3 bracket to a few seconds.

Determinism: the noise of a line comes from a generator keyed by
``(seed, exposure_seed, line_index, shutter_open)`` only, so :meth:`expose`
equals stacking :meth:`expose_line` and a line read again after a device fault
reproduces the same bytes.

References
----------
- EMVA Standard 1288, release 4.0 (2021): linear photon-transfer sensor model.
- Janesick (2007), *Photon Transfer*, SPIE Press.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mehs.errors import InputError

#: The normal draw of shot + read noise stands in for Poisson + Gaussian where the
#: sum's skewness ``λ / (λ + σ_read²)^1.5`` is at most this; above it the shot noise is
#: drawn from a Poisson law.
MAX_NORMAL_SKEW = 0.05
#: Shot noise within this many of its σ of the full well is drawn apart from the read
#: noise (which is added after the well's clip); farther below, P(clip) < 1e-9.
WELL_MARGIN_SIGMA = 6.0


def silicon_qe(wavelengths: np.ndarray) -> np.ndarray:
    """A silicon-like quantum efficiency (with grating efficiency), peak 0.7 near 660 nm.

    Falls to ~0.13 at 400 nm and ~0.04 at 1000 nm. Shape ``(bands,)`` float64.
    """
    wl = np.asarray(wavelengths, dtype=np.float64)
    return 0.7 * np.exp(-((wl - 660.0) / 200.0) ** 2)


def _skewed_span(read_e: float, skew: float) -> tuple[float, float] | None:
    """The means ``λ`` (e⁻) with ``λ / (λ + σ²)^1.5 > skew`` for read noise ``σ``: an
    interval ``(lo, hi)`` (unimodal, peak ``0.385/σ`` at ``2σ²``), or None if empty.

    Its ends are the non-negative real roots of ``skew²(λ + σ²)³ − λ² = 0``.
    """
    s2, c2 = read_e * read_e, skew * skew
    if 2.0 / 3.0 ** 1.5 <= skew * read_e:
        return None
    if s2 == 0.0:
        return 0.0, 1.0 / c2
    r = np.roots([c2, 3 * c2 * s2 - 1.0, 3 * c2 * s2 * s2, c2 * s2 ** 3])
    r = np.sort(r[np.abs(r.imag) < 1e-9 * np.abs(r).max()].real)
    r = r[r >= 0]
    return float(r[0]), float(r[-1])


RESPONSES = ("linear", "gamma", "s-curve")


@dataclass
class SensorModel:
    """Line-scan sensor: QE, shot/read/dark noise, column FPN, response and 12-bit ADC.

    Attributes
    ----------
    qe
        Per-band quantum efficiency ``(bands,)``; ``None`` → :func:`silicon_qe` of ``wavelengths``.
    wavelengths
        Band centres (nm) used for the default QE; ``None`` → the Specim IQ grid.
    gain_dn_per_e
        Conversion gain (DN per electron).
    full_well_e
        Pixel capacity; electrons above it are lost (a second saturation
        mechanism besides the ADC's 4095).
    read_noise_e, dark_current_e_per_ms
        Read noise std (e⁻) and dark current (e⁻/ms, so darks grow ∝ t).
    column_fpn_sigma
        Std (DN) of the fixed offset per (sample, band).
    black_level_dn
        Electronic offset (DN) added before the response.
    bit_depth
        ADC bits; saturation at ``2**bit_depth − 1``.
    response
        ``"linear"``, ``"gamma"``, ``"s-curve"`` or a monotonic callable mapping
        linear DN (float array) to DN on the same scale.
    gamma, s_amplitude
        Parameters of the ``"gamma"`` and ``"s-curve"`` responses.
    radiance_to_e_per_ms
        Electrons per ms per unit relative radiance at QE 1.
    seed
        Seeds the noise and the fixed pattern.
    """

    qe: np.ndarray | None = None
    gain_dn_per_e: float = 0.25
    full_well_e: float = 20000.0
    read_noise_e: float = 8.0
    dark_current_e_per_ms: float = 2.0
    column_fpn_sigma: float = 1.5
    bit_depth: int = 12
    response: str | Callable[[np.ndarray], np.ndarray] = "linear"
    radiance_to_e_per_ms: float = 400.0
    seed: int = 0
    black_level_dn: float = 32.0
    gamma: float = 0.8
    s_amplitude: float = 0.3
    wavelengths: np.ndarray | None = None
    _fpn_cache: dict = field(default_factory=dict, repr=False, compare=False)
    _inv_lut: Any = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (1 <= int(self.bit_depth) <= 16):
            raise InputError(f"bit_depth must be 1..16, got {self.bit_depth}")
        for name in ("gain_dn_per_e", "full_well_e", "radiance_to_e_per_ms"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"sensor {name} must be positive, got {v}")
        for name in ("read_noise_e", "dark_current_e_per_ms", "column_fpn_sigma", "black_level_dn"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"sensor {name} must be >= 0, got {v}")
        if float(self.bit_depth) != int(self.bit_depth):
            raise InputError(f"bit_depth must be a whole number of bits, got {self.bit_depth}")
        if isinstance(self.response, str) and self.response not in RESPONSES:
            raise InputError(f"unknown response {self.response!r}; use one of {RESPONSES} or a callable")
        # a response must rise monotonically: gamma <= 0 (or NaN) turns every pixel to 4095
        # (or 0), an S-curve amplitude >= 1 folds back; both pass through expose() unnoticed
        g = float(self.gamma)
        if self.response == "gamma" and not (np.isfinite(g) and g > 0):
            raise InputError(f"sensor gamma must be finite and > 0, got {g}")
        a = float(self.s_amplitude)
        if self.response == "s-curve" and not (np.isfinite(a) and 0 <= a < 1):
            raise InputError(f"sensor s_amplitude must be in [0, 1) for a monotonic S-curve, got {a}")
        if self.qe is not None:
            self.qe = np.asarray(self.qe, dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(self.qe) & (self.qe >= 0)):
                raise InputError("sensor qe must be finite and >= 0")

    # ------------------------------------------------------------------ basics
    @property
    def saturation_dn(self) -> int:
        """Largest ADC code (4095 at 12 bits)."""
        return (1 << int(self.bit_depth)) - 1

    def qe_for(self, bands: int, wavelengths: np.ndarray | None = None) -> np.ndarray:
        """float32 ``(bands,)`` QE, checked against the band count."""
        if self.qe is not None:
            if self.qe.size != bands:
                raise InputError(f"sensor qe has {self.qe.size} values for {bands} bands")
            return self.qe.astype(np.float32)
        if wavelengths is None:
            wavelengths = self.wavelengths
        if wavelengths is None:
            from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS
            wavelengths = SPECIM_IQ_WAVELENGTHS
        from mehs.capture.scene import check_wavelengths

        # the silicon QE is a function of λ in nm: band centres in µm would give QE ≈ 0
        wavelengths = check_wavelengths(np.asarray(wavelengths).reshape(-1), "sensor")
        if wavelengths.size != bands:
            raise InputError(f"sensor has {wavelengths.size} wavelengths for {bands} bands; "
                             "pass qe= or wavelengths= to the SensorModel")
        return silicon_qe(wavelengths).astype(np.float32)

    def signal_scale(self, bands: int, wavelengths: np.ndarray | None = None) -> np.ndarray:
        """float64 ``(bands,)``: linear DN per ms per unit radiance (``qe·scale·gain``).

        Dark-subtracted, linearised DN divided by ``t`` equals ``radiance · signal_scale``.
        """
        return (self.qe_for(bands, wavelengths).astype(np.float64)
                * self.radiance_to_e_per_ms * self.gain_dn_per_e)

    def fpn(self, samples: int, bands: int) -> np.ndarray:
        """float32 ``(samples, bands)`` column fixed-pattern offsets (DN), fixed by the seed."""
        key = (samples, bands)
        if key not in self._fpn_cache:
            rng = np.random.default_rng([int(self.seed), 0xF1C0, samples, bands])
            self._fpn_cache[key] = (rng.standard_normal((samples, bands), dtype=np.float32)
                                    * np.float32(self.column_fpn_sigma))
        return self._fpn_cache[key]

    # ---------------------------------------------------------------- response
    def response_dn(self, x: np.ndarray) -> np.ndarray:
        """Apply the response ``R`` to linear DN ``x`` (float array, any shape) → DN (float, unclipped)."""
        full = float(self.saturation_dn)
        x = np.asarray(x)
        if callable(self.response):
            return np.asarray(self.response(x))
        if self.response == "linear":
            return x
        u = np.clip(x / full, 0.0, None)
        if self.response == "gamma":
            return full * u ** self.gamma
        # s-curve: monotonic for a < 1, fixed points at 0 and full scale.
        return full * (u - self.s_amplitude * np.sin(2 * np.pi * u) / (2 * np.pi))

    def _inverse_lut(self) -> tuple[np.ndarray, np.ndarray]:
        if self._inv_lut is None:
            full = float(self.saturation_dn)
            x = np.linspace(0.0, full, 1 << 16)
            z = np.asarray(self.response_dn(x), dtype=np.float64)
            if np.any(np.diff(z) <= 0):
                raise InputError("the sensor response is not strictly increasing")
            self._inv_lut = (z, x)
        return self._inv_lut

    def inverse_response_dn(self, z: np.ndarray) -> np.ndarray:
        """Linear DN that produces DN ``z`` (inverse of :meth:`response_dn`), float64."""
        z = np.asarray(z, dtype=np.float64)
        if not callable(self.response) and self.response == "linear":
            return z
        if not callable(self.response) and self.response == "gamma":
            full = float(self.saturation_dn)
            return full * np.clip(z / full, 0.0, None) ** (1.0 / self.gamma)
        zs, xs = self._inverse_lut()
        return np.interp(z, zs, xs)

    def true_log_inverse_response(self, z: np.ndarray) -> np.ndarray:
        """Debevec–Malik's ``g(z) = ln(linear signal that produced z)``, float64.

        Defined up to an additive constant (the gauge fixed by ``g(z_mid) = 0``
        in a solver); compare curves after removing the mean difference.
        ``z = 0`` maps to ``ln`` of a tiny positive number rather than ``-inf``.
        """
        return np.log(np.maximum(self.inverse_response_dn(z), 1e-3))

    # ---------------------------------------------------------------- exposure
    def _mean_electrons(self, radiance: np.ndarray, t: float, qe: np.ndarray,
                        shutter_open: bool) -> np.ndarray:
        dark = np.float32(self.dark_current_e_per_ms * t)
        if not shutter_open:
            return np.full(radiance.shape, dark, dtype=np.float32)
        scale = np.float32(self.radiance_to_e_per_ms * t)
        lam = radiance.astype(np.float32, copy=False) * (qe * scale)
        lam += dark
        return lam

    def _check(self, radiance: np.ndarray, t: float, ndim: int) -> float:
        if radiance.ndim != ndim:
            raise InputError(f"radiance must be {ndim}-D, got shape {radiance.shape}")
        t = float(t)
        if not (np.isfinite(t) and t > 0):
            raise InputError(f"integration time must be positive, got {t} ms")
        return t

    def expected_dn(self, radiance: np.ndarray, integration_time_ms: float, *,
                    shutter_open: bool = True, include_fpn: bool = True,
                    wavelengths: np.ndarray | None = None) -> np.ndarray:
        """Noise-free DN (float32, clipped to the ADC range, not rounded).

        ``radiance`` is ``(..., samples, bands)``; the fixed pattern (deterministic)
        is included unless ``include_fpn=False``.
        """
        radiance = np.asarray(radiance)
        t = float(integration_time_ms)
        if radiance.ndim < 2 or not (np.isfinite(t) and t > 0):
            raise InputError("expected_dn needs (..., samples, bands) radiance and t > 0")
        samples, bands = radiance.shape[-2:]
        qe = self.qe_for(bands, wavelengths)
        lam = np.minimum(self._mean_electrons(radiance, t, qe, shutter_open), self.full_well_e)
        x = lam * np.float32(self.gain_dn_per_e) + np.float32(self.black_level_dn)
        if include_fpn:
            x = x + self.fpn(samples, bands)
        z = self.response_dn(np.maximum(x, 0))
        return np.clip(z, 0, self.saturation_dn).astype(np.float32)

    def _electrons(self, lam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """float32 electrons read out of pixels of mean ``lam`` (float32, any shape):
        shot noise clipped at the full well, then read noise (see the module notes)."""
        read = np.float32(self.read_noise_e)
        fw = np.float32(self.full_well_e)
        n = rng.standard_normal(lam.shape, dtype=np.float32)
        # Shot + read noise as one normal draw (variance λ + σ²), where neither the
        # Poisson law's skew nor the well's clip can show.
        e = lam + np.sqrt(lam + read * read) * n
        # The skewness λ/(λ + σ²)^1.5 of Poisson + Gaussian peaks at 2/(3^1.5·σ) =
        # 0.385/σ (λ = 2σ²): below 7.7 e⁻ of read noise some λ need the exact Poisson
        # draw (clipped at the well on its own: its tail reaches far beyond 6√λ for small λ).
        exact = None
        span = _skewed_span(float(read), MAX_NORMAL_SKEW)
        if span is not None:
            exact = (lam > np.float32(span[0])) & (lam < np.float32(span[1]))
            if exact.any():
                e[exact] = (np.minimum(rng.poisson(lam[exact]).astype(np.float32), fw)
                            + read * n[exact])
        # Near the well the shot electrons clip alone (the well holds charge; the read
        # noise is added at read-out): a second, independent draw for the read noise.
        # λ + k√λ = FW  ⇔  √λ = √(k²/4 + FW) − k/2.
        k = WELL_MARGIN_SIGMA
        near = lam >= np.float32((np.sqrt(k * k / 4 + float(fw)) - k / 2) ** 2)
        if exact is not None:
            near &= ~exact
        if near.any():
            ln = lam[near]
            shot = np.minimum(ln + np.sqrt(ln) * n[near], fw)
            e[near] = shot + read * rng.standard_normal(ln.size, dtype=np.float32)
        return e

    def expose_line(self, radiance_line: np.ndarray, integration_time_ms: float, *,
                    exposure_seed: int = 0, line_index: int = 0, shutter_open: bool = True,
                    wavelengths: np.ndarray | None = None) -> np.ndarray:
        """Expose one spatial line.

        Parameters
        ----------
        radiance_line
            ``(samples, bands)`` relative radiance (ignored when the shutter is closed).
        integration_time_ms
            Exposure time (ms).
        exposure_seed, line_index
            With the sensor seed and the shutter state, key the noise generator.

        Returns
        -------
        ndarray
            uint16 ``(samples, bands)`` DN.
        """
        radiance_line = np.asarray(radiance_line)
        t = self._check(radiance_line, integration_time_ms, 2)
        samples, bands = radiance_line.shape
        qe = self.qe_for(bands, wavelengths)
        key = [int(self.seed), int(exposure_seed), int(line_index), int(bool(shutter_open))]
        if min(key) < 0:
            raise InputError(f"sensor seed, exposure seed and line index must be >= 0, got {key[:3]}")
        rng = np.random.default_rng(key)
        lam = self._mean_electrons(radiance_line, t, qe, shutter_open)
        if not np.all(np.isfinite(lam)) or np.any(lam < 0):
            raise InputError("radiance must be finite and >= 0")
        e = self._electrons(lam, rng)
        x = e * np.float32(self.gain_dn_per_e)
        x += np.float32(self.black_level_dn)
        x += self.fpn(samples, bands)
        np.maximum(x, 0, out=x)
        z = self.response_dn(x)
        z = np.rint(z, out=z if z is x else None)
        return np.clip(z, 0, self.saturation_dn).astype(np.uint16)

    def expose(self, radiance: np.ndarray, integration_time_ms: float, *, exposure_seed: int = 0,
               shutter_open: bool = True, line_offset: int = 0,
               wavelengths: np.ndarray | None = None) -> np.ndarray:
        """Expose a cube line by line: uint16 ``(lines, samples, bands)``.

        Identical to stacking :meth:`expose_line` with ``line_index = line_offset + i``.
        """
        radiance = np.asarray(radiance)
        t = self._check(radiance, integration_time_ms, 3)
        out = np.empty(radiance.shape, dtype=np.uint16)
        for i in range(radiance.shape[0]):
            out[i] = self.expose_line(radiance[i], t, exposure_seed=exposure_seed,
                                      line_index=line_offset + i, shutter_open=shutter_open,
                                      wavelengths=wavelengths)
        return out


def exposure_seed_for(integration_time_ms: float) -> int:
    """The exposure seed the simulated camera uses: the integration time in ns.

    Keying the noise on the time (not on a frame counter) makes a line read
    again after a fault, or on ``--resume``, reproduce the same bytes.
    """
    return int(round(float(integration_time_ms) * 1e6))
