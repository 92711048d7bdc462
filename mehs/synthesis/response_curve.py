"""The camera response curve type: ``g(z) = ln(E·Δt)`` per level, its gauge, and its file
format (``response.json``, :data:`FORMAT`). Split from :mod:`mehs.synthesis.response` (the
recovery), which re-exports every name here.

A curve read from a file must rise with the level: a ``g`` that falls anywhere (a
hand-edited file, or another tool's curve with a fold) would map two raw levels to one
radiance and invert the order of pixels, so :meth:`ResponseCurve.load` refuses it, naming
the file and the first falling level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import FormatError, InputError

FORMAT = "mehs-response/1"


@dataclass
class ResponseCurve:
    """A camera response curve ``g(z) = ln(E·Δt)``.

    Attributes
    ----------
    g
        float64 ``(L,)`` (one curve for all bands) or ``(bands, L)``; ``L = 2**bit_depth``.
    bit_depth
        Sensor bit depth, 8–16.
    method
        ``"debevec1997"`` (recovered) or ``"linear"`` (``g = ln z``).
    smoothness
        λ used for the recovery (None for linear).
    weighting
        Name of the weighting used (``"custom"`` for a callable).
    wavelengths
        Band centres (nm) the per-band curves belong to, or None.
    parameters
        Anything else worth keeping (samples, seed, exposure times, solver stats).
    """

    g: np.ndarray
    bit_depth: int
    method: str = "debevec1997"
    smoothness: float | None = None
    weighting: str = "hat"
    wavelengths: np.ndarray | None = None
    parameters: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.bit_depth = _check_bit_depth(self.bit_depth)
        g = np.asarray(self.g, dtype=np.float64)
        if g.ndim not in (1, 2) or g.shape[-1] != self.levels:
            raise InputError(f"response curve must have shape (levels,) or (bands, levels) "
                             f"with levels = {self.levels}, got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise InputError("response curve contains non-finite values")
        self.g = g
        if self.wavelengths is not None:
            self.wavelengths = np.asarray(self.wavelengths, dtype=np.float64).reshape(-1)
            if not self.shared and self.wavelengths.size != g.shape[0]:
                raise InputError(f"{self.wavelengths.size} wavelengths for {g.shape[0]} curves")

    @property
    def levels(self) -> int:
        return 1 << self.bit_depth

    @property
    def shared(self) -> bool:
        """True when one curve serves every band."""
        return self.g.ndim == 1

    @property
    def is_linear(self) -> bool:
        return self.method == "linear"

    @property
    def bands(self) -> int | None:
        return None if self.shared else self.g.shape[0]

    def fingerprint(self) -> str:
        """sha256 of the curve's levels (``g`` to 1e-9, its shape and bit depth): the same
        curve saved and loaded, or recovered again from the same data, gives the same
        value. A calibration records it, since radiance is only right under the curve the
        calibration was made with."""
        import hashlib

        h = hashlib.sha256(f"{self.bit_depth}:{self.g.shape}:".encode())
        h.update(np.ascontiguousarray(np.round(self.g, 9), dtype="<f8").tobytes())
        return h.hexdigest()

    def table(self, bands: int | None = None) -> np.ndarray:
        """g as float64 (C, L): C = 1 for a shared curve, else one row per band.

        ``bands`` (when given) is checked against a per-band curve.
        """
        if self.shared:
            return self.g[None, :]
        if bands is not None and bands != self.g.shape[0]:
            raise InputError(f"response curve has {self.g.shape[0]} bands, data has {bands}")
        return self.g

    def log_exposure(self, z: np.ndarray) -> np.ndarray:
        """``g(z)`` for integer levels ``z`` of shape (..., bands) (or any shape if shared).

        Levels are clipped to 0..L−1. Returns float64 of ``z``'s shape.
        """
        z = np.clip(np.asarray(z), 0, self.levels - 1).astype(np.intp)
        if self.shared:
            return self.g[z]
        nb = self.g.shape[0]
        if z.shape[-1] != nb:
            raise InputError(f"last axis of z has {z.shape[-1]} bands, curve has {nb}")
        return self.g[np.arange(nb), z]

    def exposure(self, z: np.ndarray) -> np.ndarray:
        """``exp(g(z))``: the linearised sensor value (linear-equivalent DN)."""
        return np.exp(self.log_exposure(z))

    # --------------------------------------------------------- construction
    @classmethod
    def linear(cls, bit_depth: int = 12, *, bands: int | None = None,
               wavelengths: np.ndarray | None = None) -> "ResponseCurve":
        """The linear-sensor curve ``g(z) = ln z`` (dark already subtracted).

        Level 0 (at or below black) is given ``ln 0.5``: half a DN is the
        smallest positive value a rounded level can stand for.
        """
        L = 1 << _check_bit_depth(bit_depth)
        g = np.log(np.maximum(np.arange(L, dtype=np.float64), 0.5))
        if bands is not None:
            g = np.repeat(g[None], bands, axis=0)
        return cls(g, bit_depth, method="linear", smoothness=None, weighting="hat",
                   wavelengths=wavelengths)

    # --------------------------------------------------------------- storage
    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "method": self.method, "bit_depth": self.bit_depth,
                "levels": self.levels, "shared": self.shared,
                "smoothness": self.smoothness, "weighting": self.weighting,
                "gauge": "g(Z_mid) = ln(Z_mid)",
                "wavelengths": None if self.wavelengths is None else self.wavelengths.tolist(),
                "parameters": self.parameters,
                "g": self.g.tolist()}

    def save(self, path: str | Path) -> Path:
        """Write the curve and its parameters as JSON (atomically)."""
        from mehs.io.atomic import write_json_atomic

        # json writes floats at repr precision: a saved curve reloads bit-identically
        return write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "ResponseCurve":
        """Read a curve written by :meth:`save`."""
        from mehs.io.jsondoc import read_json_document

        path = Path(path)
        d = read_json_document(path, FORMAT, "response curve")
        try:
            curve = cls(np.asarray(d["g"], dtype=np.float64), int(d["bit_depth"]),
                        method=str(d.get("method", "debevec1997")),
                        smoothness=d.get("smoothness"), weighting=str(d.get("weighting", "hat")),
                        wavelengths=d.get("wavelengths"), parameters=d.get("parameters") or {})
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"bad response curve ({exc})", path) from None
        problem = curve.monotonic_problem()
        if problem:
            raise FormatError(f"bad response curve: {problem}", path)
        return curve

    def monotonic_problem(self) -> str | None:
        """Where ``g`` falls, as a sentence, or None when it never falls (equal neighbours
        are allowed: a floored end). A falling ``g`` maps two raw levels to one linear
        value and reverses the order of brighter and darker pixels between them: no
        sensor's response does that, so such a curve (hand-edited, another tool's) is
        refused, not merged."""
        g = self.table()
        falls = np.diff(g, axis=1) < 0                      # (C, L-1)
        if not falls.any():
            return None
        band, z = np.argwhere(falls)[0]
        where = "" if self.shared else f" of band {int(band)}" + (
            f" ({self.wavelengths[band]:g} nm)" if self.wavelengths is not None else "")
        return (f"g{where} falls from level {int(z)} to {int(z) + 1} ({g[band, z]:.6g} -> "
                f"{g[band, z + 1]:.6g}; {int(falls.sum())} falling level(s) in all): a "
                "response curve must rise with the level (monotonic)")


def _check_bit_depth(bit_depth: Any) -> int:
    try:
        b = int(bit_depth)
    except (TypeError, ValueError):
        raise InputError(f"bit depth must be an integer, got {bit_depth!r}") from None
    if b != bit_depth or not 8 <= b <= 16:
        raise InputError(f"bit depth must be 8..16, got {bit_depth!r}")
    return b
