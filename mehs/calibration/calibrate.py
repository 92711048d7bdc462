"""Radiometric calibration: camera DN/ms → spectral radiance, per band and per column.

Fused HDR data are linearised, dark-subtracted DN per ms: the scene radiance
times the camera's responsivity (quantum efficiency × optics × gain), which
varies by a factor of several across 400–1000 nm and a few per cent across the
slit. A capture of a reference of known spectral radiance ``L_ref`` gives the
responsivity

    R[s, b] = (DN/ms)[s, b] / L_ref[b]        (s: spatial column, b: band)

and every later cube is calibrated by ``L = (DN/ms) / R`` — the flat field is
part of ``R`` wherever the reference filled the slit. Two references, both lab
practice (design.md §3.5):

- :func:`calibrate_panel_relative` — a diffuse panel of known reflectance
  ``ρ(λ)`` under an illuminant of known *relative* SPD ``S(λ)``:
  ``L_ref = ρ·S/π`` up to one unknown scale → **relative radiance** (right
  spectral shapes and ratios, unknown absolute level);
- :func:`calibrate_source_absolute` — a calibrated source (integrating sphere,
  standard lamp + panel) whose certificate gives ``L_ref`` in
  W·sr⁻¹·m⁻²·nm⁻¹ → **absolute radiance**.

The reference region is either the capture's white-reference line
(``region="white"``: each exposure's WHITEREF, linearised with the response
curve; the longest unsaturated exposure is used, the others give the
uncertainty), or scan lines of the fused capture (``region="frame"`` or
``"lines:A-B"``: a sphere filling the view; the spread over lines gives the
uncertainty).

References
----------
- Schaepman-Strub, G. et al. (2006). Reflectance quantities in optical remote
  sensing — definitions and case studies. RSE 103, 27–42 (``L = ρ E / π`` for a
  Lambertian panel).
- Yoon, H. W. and Gibson, C. E. (2011). Spectral irradiance calibrations. NIST
  SP 250-89 (lamp certificates, uncertainty propagation).
"""

from __future__ import annotations

import datetime as _dt
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.calibration.spectra import Spectrum, band_average
from mehs.errors import FormatError, InputError

FORMAT = "mehs-calibration/1"
UNIT_ABSOLUTE = "W sr-1 m-2 nm-1"
UNIT_RELATIVE = "relative radiance"
UNIT_UNCALIBRATED = "DN/ms (uncalibrated)"


@dataclass
class Calibration:
    """Per-band (and per-column) responsivity with its uncertainty and provenance.

    Attributes
    ----------
    responsivity
        float64 ``(samples, bands)`` (flat-fielded) or ``(1, bands)``: DN/ms per unit radiance.
    uncertainty
        float64, same shape: relative standard uncertainty of ``responsivity``.
    wavelengths, fwhm
        Band centres / widths (nm) of the camera the calibration belongs to.
    unit
        Radiance unit of calibrated data: :data:`UNIT_ABSOLUTE` or :data:`UNIT_RELATIVE`.
    method
        ``"panel-relative"`` or ``"source-absolute"``.
    camera
        ``{"id", "binning", "samples", "bit_depth"}`` (id/binning may be None when unknown).
    response
        The response curve used to linearise the reference capture (``method``,
        ``sha256`` of its file or None for the linear curve).
    sources
        ``[{"role", "path", "sha256"}]``: every input file.
    created
        ISO 8601 UTC time.
    bands
        int ``(k,)`` indices (into ``wavelengths``) of the calibrated bands — all of
        them, or those the reference spectrum covers (a colour-science illuminant ends
        at 780 nm; a 1000 nm camera is calibrated over 397–774 nm then). Calibrated
        cubes hold these bands only; ``responsivity`` has one column per calibrated band.
    """

    responsivity: np.ndarray
    uncertainty: np.ndarray
    wavelengths: np.ndarray
    unit: str
    method: str
    fwhm: np.ndarray | None = None
    camera: dict[str, Any] = field(default_factory=dict)
    response: dict[str, Any] = field(default_factory=dict)
    sources: list[dict[str, Any]] = field(default_factory=list)
    created: str = ""
    parameters: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    bands: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.responsivity = np.atleast_2d(np.asarray(self.responsivity, dtype=np.float64))
        self.uncertainty = np.atleast_2d(np.asarray(self.uncertainty, dtype=np.float64))
        self.wavelengths = np.asarray(self.wavelengths, dtype=np.float64).reshape(-1)
        r = self.responsivity
        where = f" ({self.path})" if self.path else ""
        nw = self.wavelengths.size
        self.bands = (np.arange(nw) if self.bands is None
                      else np.asarray(self.bands, dtype=np.int64).reshape(-1))
        if (self.bands.size == 0 or np.any(np.diff(self.bands) <= 0) or self.bands[0] < 0
                or self.bands[-1] >= nw):
            raise InputError(f"calibrated bands must be ascending indices into the {nw} "
                             f"wavelengths{where}")
        if r.ndim != 2 or r.shape[1] != self.bands.size:
            raise InputError(f"responsivity must be (samples, {self.bands.size}), got "
                             f"{r.shape}{where}")
        bad = ~np.isfinite(r) | (r <= 0)
        if bad.any():
            b = np.flatnonzero(bad.any(axis=0))
            raise InputError(f"responsivity is NaN, zero or negative in {b.size} band(s), first "
                             f"{self.wavelengths[self.bands[b[0]]]:.2f} nm{where}: the reference had "
                             "no usable signal there (saturated, too dark, or no power at those "
                             "wavelengths)")
        if self.uncertainty.shape != r.shape:
            raise InputError(f"uncertainty shape {self.uncertainty.shape} != responsivity "
                             f"shape {r.shape}{where}")
        if self.unit not in (UNIT_ABSOLUTE, UNIT_RELATIVE):
            raise InputError(f"unknown calibration unit {self.unit!r}{where}")

    # ------------------------------------------------------------------ use
    def check_compatible(self, wavelengths: np.ndarray, samples: int, *, camera_id: str | None = None,
                         binning: Any = None, source: Any = None, bit_depth: int | None = None,
                         response: Any = None) -> None:
        """Refuse data of another camera, band set, width, binning or bit depth, or linearised
        by another kind of response curve (an :class:`InputError` naming both).

        The responsivity is DN/ms *as linearised by the calibration's curve*: under another
        curve the radiance errs by the two curves' ratio (a gamma sensor calibrated linear
        and fused with its recovered curve: 26–38 %). A linear against a non-linear curve
        is refused; two different non-linear curves (``response``, a
        :class:`~mehs.synthesis.response.ResponseCurve`) give a warning, as two recoveries
        of one sensor's curve differ a little.
        """
        from mehs.bandmeta import check_same_bands

        me = f"calibration {self.path}" if self.path else "the calibration"
        check_same_bands(self.wavelengths, wavelengths, me, "the data", source)
        if self.responsivity.shape[0] not in (1, int(samples)):
            raise InputError(f"{me} has {self.responsivity.shape[0]} spatial columns, the data "
                             f"{samples} (another binning or sensor width?)", source)
        mine = self.camera.get("id")
        if mine and camera_id and str(mine) != str(camera_id):
            raise InputError(f"{me} is for camera {mine!r}, the data are from {camera_id!r}", source)
        mb = self.camera.get("binning")
        if mb is not None and binning is not None and list(np.atleast_1d(mb)) != list(np.atleast_1d(binning)):
            raise InputError(f"{me} was made at binning {mb}, the data at {binning}", source)
        bd = self.camera.get("bit_depth")
        if bd is not None and bit_depth is not None and int(bd) != int(bit_depth):
            # Mono12 against an MSB-aligned Mono16 is a factor 16 in every DN
            raise InputError(f"{me} was made from {bd}-bit data, the data are {bit_depth}-bit",
                             source)
        if response is not None and self.response.get("method"):
            self._check_response(response, me, source)

    def _check_response(self, curve: Any, me: str, source: Any) -> None:
        import warnings

        rec = self.response
        was_linear = rec["method"] == "linear"
        if was_linear != bool(curve.is_linear):
            made = "a linear response" if was_linear else f"a {rec['method']} response curve"
            now = "a linear response" if curve.is_linear else f"a {curve.method} response curve"
            hint = ("--response linear" if was_linear else
                    f"--response {rec['path']}" if rec.get("path") else "the curve it was made with")
            raise InputError(f"{me} was made with {made}, the data are linearised with {now}: "
                             f"the radiance would err by the curves' ratio; fuse with {hint}, "
                             "or calibrate again with this curve", source)
        fp = rec.get("g_sha256")
        if not was_linear and fp and fp != curve.fingerprint():
            where = f" ({rec['path']})" if rec.get("path") else ""
            warnings.warn(f"{me} was made with another response curve{where} than the data are "
                          "linearised with: the radiance errs by the two curves' ratio; reuse "
                          "the calibration's curve (--response)", stacklevel=4)

    @property
    def complete(self) -> bool:
        """True when every band of the camera is calibrated."""
        return self.bands.size == self.wavelengths.size

    @property
    def calibrated_wavelengths(self) -> np.ndarray:
        return self.wavelengths[self.bands]

    def apply(self, dn_per_ms: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
        """Radiance ``(lines, samples, k)`` of the calibrated bands from linearised DN/ms
        ``(lines, samples, bands)``; ``out`` (in place) only when every band is calibrated."""
        x = np.asarray(dn_per_ms)
        if x.ndim != 3 or x.shape[2] != self.wavelengths.size:
            raise InputError(f"calibrate needs (lines, samples, {self.wavelengths.size}), got {x.shape}")
        inv = (1.0 / self.responsivity).astype(np.float32)
        if not self.complete:
            return (x[..., self.bands] * inv[None]).astype(np.float32)
        if out is None:
            return (x * inv[None]).astype(np.float32)
        np.multiply(x, inv[None], out=out)
        return out

    def summary(self) -> dict[str, Any]:
        """Small JSON-able description (recorded in fusion summaries and manifests)."""
        return {"unit": self.unit, "method": self.method, "camera": self.camera,
                "path": None if self.path is None else str(self.path),
                "sha256": self.parameters.get("file_sha256"),
                "median_uncertainty": float(np.median(self.uncertainty)),
                "calibrated_nm": [float(self.calibrated_wavelengths[0]),
                                  float(self.calibrated_wavelengths[-1])],
                "bands": int(self.bands.size), "created": self.created}

    # -------------------------------------------------------------- storage
    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "unit": self.unit, "method": self.method,
                "created": self.created, "camera": self.camera, "response": self.response,
                "sources": self.sources, "parameters": self.parameters,
                "wavelengths": self.wavelengths.tolist(),
                "fwhm": None if self.fwhm is None else np.asarray(self.fwhm).tolist(),
                "bands": None if self.complete else self.bands.tolist(),
                "responsivity_shape": list(self.responsivity.shape),
                "responsivity": [float(f"{v:.9g}") for v in self.responsivity.ravel()],
                "uncertainty": [float(f"{v:.4g}") for v in self.uncertainty.ravel()]}

    def save(self, path: str | Path) -> Path:
        """Write the calibration as JSON, atomically."""
        from mehs.io.atomic import write_json_atomic

        return write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read a calibration written by :meth:`save` (errors name the file)."""
        from mehs.io.atomic import sha256_file

        from mehs.io.jsondoc import read_json_document

        path = Path(path)
        d = read_json_document(path, FORMAT, "calibration")
        try:
            shape = tuple(int(v) for v in d["responsivity_shape"])
            r = np.asarray(d["responsivity"], dtype=np.float64).reshape(shape)
            u = np.asarray(d["uncertainty"], dtype=np.float64).reshape(shape)
            params = dict(d.get("parameters") or {})
            params["file_sha256"] = sha256_file(path)
            return cls(r, u, d["wavelengths"], str(d["unit"]), str(d["method"]),
                       fwhm=d.get("fwhm"), camera=d.get("camera") or {},
                       response=d.get("response") or {}, sources=d.get("sources") or [],
                       created=str(d.get("created", "")), parameters=params, path=path,
                       bands=d.get("bands"))
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"bad calibration file ({exc})", path) from None
        except InputError as exc:
            raise FormatError(exc.problem, path) from None


def bracket_camera_id(bracket) -> str | None:
    """The camera's id recorded with a capture (scene.json ``device.camera.id``/``serial``), if any."""
    meta = bracket.metadata if isinstance(bracket.metadata, dict) else {}
    dev = meta.get("device") if isinstance(meta.get("device"), dict) else {}
    cam = dev.get("camera") if isinstance(dev.get("camera"), dict) else {}
    for key in ("id", "serial", "camera_id"):
        if cam.get(key):
            return str(cam[key])
    return None


# ------------------------------------------------------------- measurement
def _white_dn_per_ms(bracket, response, saturation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(samples, bands) DN/ms of the white-reference line and its relative uncertainty."""
    from mehs.synthesis.fuse import _dark_mode, _lineariser

    if any(w is None for w in bracket.white):
        raise InputError("the capture has no white reference line in every exposure; use "
                         "--region frame (a reference filling the view)", bracket.source)
    L = 1 << bracket.bit_depth
    lin = _lineariser(response, _dark_mode(response), bracket.bit_depth,
                      [d is not None for d in bracket.darks])
    est, use = [], []
    for j, (w, d, t) in enumerate(zip(bracket.white, bracket.darks, bracket.times_ms)):
        w = np.asarray(w, dtype=np.float64)
        dk = np.zeros_like(w) if d is None else np.asarray(d, dtype=np.float64)
        y = np.asarray(lin(w, dk, j), dtype=np.float64)
        est.append(y / t)
        # enough signal to matter, far enough from saturation for the mean of lines
        use.append((w < np.minimum(saturation, 0.98 * (L - 1))[None, :]) & ((w - dk) > 50))
    est, use = np.stack(est), np.stack(use)
    if not use.any(axis=0).all():
        s, b = np.argwhere(~use.any(axis=0))[0]
        raise InputError(f"the white reference is saturated or too dark in every exposure at "
                         f"column {s}, {bracket.wavelengths[b]:.2f} nm", bracket.source)
    # the longest usable exposure has the best SNR
    last = (use.shape[0] - 1) - np.argmax(use[::-1], axis=0)
    best = np.take_along_axis(est, last[None], axis=0)[0]
    n = use.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(use, est, 0).sum(0) / np.maximum(n, 1)
        var = np.where(use, (est - mean) ** 2, 0).sum(0) / np.maximum(n - 1, 1)
        rel = np.sqrt(var / np.maximum(n, 1)) / np.abs(best)
    fill = np.median(rel[n >= 2]) if np.any(n >= 2) else 0.01
    rel = np.where(n >= 2, rel, fill)
    return best, rel


def _region_rows(region: Any, bracket) -> np.ndarray | None:
    """Scan lines of ``region`` (``"frame"``, ``"lines:A-B"``), or None for ``"white"``.

    Checked before any work: a misspelt region (``"Frame"``, ``"whites"``) once
    failed with an IndexError deep in the calibration, and any ``"<word>:A-B"``
    (``"frame:0-9"``) was silently taken for ``"lines:A-B"``.
    """
    nl = bracket.shape[0]
    if region == "white":
        return None
    if region == "frame":
        return np.arange(nl)
    m = re.fullmatch(r"lines:\s*(\d+)\s*-\s*(\d+)\s*", region) if isinstance(region, str) else None
    if m is None:
        raise InputError(f"region must be 'white', 'frame' or 'lines:A-B' (0-based, inclusive), "
                         f"got {region!r}")
    a, b = int(m.group(1)), int(m.group(2))
    if not (0 <= a <= b < nl):
        raise InputError(f"region lines {a}-{b} outside the capture's 0-{nl - 1}", bracket.source)
    return np.arange(a, b + 1)


def _frame_dn_per_ms(bracket, response, rows: np.ndarray,
                     saturation) -> tuple[np.ndarray, np.ndarray]:
    """DN/ms of the scan lines ``rows`` (from :func:`_region_rows`) of the fused frame."""
    from mehs.synthesis.fuse import fuse_bracket

    res = fuse_bracket(bracket, response=response, ghosts="off", saturation=saturation,
                       check_response=False)
    x = np.asarray(res.radiance.data, dtype=np.float64)[rows]
    ok = (res.mask[rows] == 0)[..., None] & np.isfinite(x) & (x > 0)
    n = ok.sum(axis=0)
    if np.any(n < 1):
        s, b = np.argwhere(n < 1)[0]
        raise InputError(f"no usable reference line at column {s}, "
                         f"{bracket.wavelengths[b]:.2f} nm (saturated in every exposure?)",
                         bracket.source)
    mean = np.where(ok, x, 0).sum(0) / n
    var = np.where(ok, (x - mean) ** 2, 0).sum(0) / np.maximum(n - 1, 1)
    rel = np.sqrt(var / n) / mean
    return mean, rel


def _reference_bands(bracket, spectrum: Spectrum, what: str, partial: bool) -> np.ndarray:
    fw = bracket.exposures[0].fwhm
    return band_average(spectrum, bracket.wavelengths, fw, what=what, partial=partial)


def _calibrate(bracket, l_ref: np.ndarray, ref_unc: np.ndarray, *, unit: str, method: str,
               region: str, response: Any, per_column: bool, sources: list[dict],
               camera_id: str | None, saturation: float | np.ndarray | None) -> Calibration:
    from mehs.synthesis.response import ResponseCurve

    rows = _region_rows(region, bracket)   # a bad region is refused before any work
    nb = bracket.shape[2]
    L = 1 << bracket.bit_depth
    sat = np.broadcast_to(np.asarray(0.98 * (L - 1) if saturation is None else saturation,
                                     dtype=np.float64), (nb,))
    if isinstance(response, ResponseCurve):
        curve, resp_info = response, {"method": response.method, "sha256": None}
    elif response in (None, "linear"):
        curve, resp_info = ResponseCurve.linear(bracket.bit_depth), {"method": "linear", "sha256": None}
    else:
        from mehs.io.atomic import sha256_file

        curve = ResponseCurve.load(response)
        resp_info = {"method": curve.method, "path": str(response), "sha256": sha256_file(response)}
    resp_info["g_sha256"] = curve.fingerprint()
    if rows is None:
        dn, rel = _white_dn_per_ms(bracket, curve, sat)
    else:
        dn, rel = _frame_dn_per_ms(bracket, curve, rows, sat)
    if not per_column:
        rel = np.sqrt(np.mean(rel ** 2, axis=0) / dn.shape[0])[None]
        dn = dn.mean(axis=0, keepdims=True)
    keep = np.flatnonzero(np.isfinite(l_ref))
    if keep.size == 0:
        raise InputError("the reference spectrum covers none of the camera's bands")
    if np.any(np.diff(keep) != 1):
        raise InputError("the reference spectrum leaves a gap inside the camera's bands")
    dn, rel, l_ref, ref_unc = dn[:, keep], rel[:, keep], l_ref[keep], ref_unc[keep]
    zero = l_ref <= 0
    if zero.any():
        k = int(np.flatnonzero(zero)[0])
        raise InputError(f"the reference radiance is zero at {bracket.wavelengths[keep[k]]:.2f} nm "
                         f"({int(zero.sum())} band(s)): it cannot calibrate those bands")
    resp = dn / l_ref[None, :]
    unc = np.sqrt(rel ** 2 + ref_unc[None, :] ** 2)
    e0 = bracket.exposures[0]
    cam = {"id": camera_id or bracket_camera_id(bracket), "binning": e0.binning,
           "samples": int(bracket.shape[1]), "bit_depth": int(bracket.bit_depth)}
    return Calibration(resp, unc, bracket.wavelengths, unit, method, fwhm=e0.fwhm, camera=cam,
                       bands=keep,
                       response=resp_info, sources=sources,
                       created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                       parameters={"region": region, "per_column": per_column,
                                   "times_ms": bracket.times_ms.tolist(),
                                   "reference_band_values": l_ref.tolist()})


def _capture_sources(bracket) -> list[dict]:
    from mehs.io.atomic import sha256_file

    out = []
    src = Path(bracket.source) if bracket.source else None
    if src is not None and (src / "scene.json").is_file():
        out.append({"role": "capture", "path": str(src / "scene.json"),
                    "sha256": sha256_file(src / "scene.json")})
    for e in bracket.exposures:
        p = getattr(e, "source", None)
        if p is not None and Path(p).is_file():
            out.append({"role": "capture", "path": str(p), "sha256": sha256_file(p)})
    return out


def _spec_source(role: str, spec: Spectrum) -> dict:
    from mehs.io.atomic import sha256_file

    p = Path(spec.source)
    return {"role": role, "path": spec.source, "sha256": sha256_file(p) if p.is_file() else None}


def calibrate_panel_relative(bracket, panel: Spectrum, illuminant: Spectrum, *,
                             region: str = "white", response: Any = None, per_column: bool = True,
                             camera_id: str | None = None, partial: bool = False,
                             saturation: float | np.ndarray | None = None) -> Calibration:
    """Relative calibration from a diffuse panel ``ρ(λ)`` under an illuminant of relative SPD ``S(λ)``.

    ``L_ref = ρ·S/π`` per band (band-averaged over the camera's spectral
    response), with ``S`` scaled to a mean of 1 over 400–700 nm (the absolute
    level is unknown, so calibrated data are in :data:`UNIT_RELATIVE`). ``partial``:
    calibrate the bands the spectra cover (a contiguous range) instead of refusing.
    """
    rho = _reference_bands(bracket, panel, "panel reflectance", partial)
    s = _reference_bands(bracket, illuminant, "illuminant SPD", partial)
    vis = (bracket.wavelengths >= 400) & (bracket.wavelengths <= 700)
    vis &= np.isfinite(s)
    norm = s[vis].mean() if vis.any() else np.nanmean(s)
    if not norm > 0:
        raise InputError(f"illuminant ({illuminant.source}) has no power in 400-700 nm")
    l_ref = rho * (s / norm) / np.pi
    unc = np.zeros_like(l_ref)
    if panel.uncertainty is not None:
        unc = np.interp(bracket.wavelengths, panel.wavelengths, panel.uncertainty)
    sources = _capture_sources(bracket) + [_spec_source("panel", panel),
                                           _spec_source("illuminant", illuminant)]
    return _calibrate(bracket, l_ref, unc, unit=UNIT_RELATIVE, method="panel-relative",
                      region=region, response=response, per_column=per_column, sources=sources,
                      camera_id=camera_id, saturation=saturation)


def calibrate_source_absolute(bracket, source: Spectrum, *, region: str = "frame",
                              response: Any = None, per_column: bool = True,
                              camera_id: str | None = None, partial: bool = False,
                              saturation: float | np.ndarray | None = None) -> Calibration:
    """Absolute calibration from a source of known spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹).

    The certificate's relative uncertainty (third column) is propagated. ``partial``:
    calibrate the bands the certificate covers instead of refusing.
    """
    l_ref = _reference_bands(bracket, source, "source radiance", partial)
    unc = np.zeros_like(l_ref)
    if source.uncertainty is not None:
        unc = np.interp(bracket.wavelengths, source.wavelengths, source.uncertainty)
    sources = _capture_sources(bracket) + [_spec_source("source", source)]
    return _calibrate(bracket, l_ref, unc, unit=UNIT_ABSOLUTE, method="source-absolute",
                      region=region, response=response, per_column=per_column, sources=sources,
                      camera_id=camera_id, saturation=saturation)
