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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.calibration.measure import region_rows as _region_rows
from mehs.calibration.spectra import Spectrum, band_average
from mehs.errors import FormatError, InputError

FORMAT = "mehs-calibration/1"
UNIT_ABSOLUTE = "W sr-1 m-2 nm-1"
UNIT_RELATIVE = "relative radiance"
UNIT_UNCALIBRATED = "DN/ms (uncalibrated)"
#: fields every calibration file must hold (what :meth:`Calibration.to_dict` writes)
_REQUIRED = ("unit", "method", "camera", "response", "wavelengths", "responsivity_shape",
             "responsivity", "uncertainty")


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
        u = self.uncertainty
        bad = ~np.isfinite(u) | (u < 0)
        if bad.any():
            b = np.flatnonzero(bad.any(axis=0))
            raise InputError(f"uncertainty is NaN, infinite or negative in {b.size} band(s), "
                             f"first {self.wavelengths[self.bands[b[0]]]:.2f} nm{where}")
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
        ms = self.camera.get("samples")
        if ms is not None and int(ms) != int(samples):
            # one responsivity per band fits any width, but a binned or cropped sensor
            # sums other pixels into a DN: the reference's width is the camera's
            raise InputError(f"{me} was made on {ms} spatial columns, the data have {samples} "
                             "(another binning or sensor window?)", source)
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
        missing = [k for k in _REQUIRED if k not in d]
        if missing:
            raise FormatError(f"calibration file lacks {', '.join(missing)} (edited by hand? "
                              "make it again with mehs calibrate)", path)
        if not isinstance(d["camera"], dict) or d["camera"].get("samples") is None:
            # without its camera a calibration would be applied to any camera, width, binning
            raise FormatError("calibration file's camera has no 'samples' (edited by hand? "
                              "make it again with mehs calibrate)", path)
        try:
            shape = tuple(int(v) for v in d["responsivity_shape"])
            r = np.asarray(d["responsivity"], dtype=np.float64).reshape(shape)
            u = np.asarray(d["uncertainty"], dtype=np.float64).reshape(shape)
            params = dict(d.get("parameters") or {})
            params["file_sha256"] = sha256_file(path)
            return cls(r, u, d["wavelengths"], str(d["unit"]), str(d["method"]),
                       fwhm=d.get("fwhm"), camera=d["camera"],
                       response=d["response"] or {}, sources=d.get("sources") or [],
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


def _reference_bands(bracket, spectrum: Spectrum, what: str, partial: bool,
                     smooth: bool = False) -> np.ndarray:
    fw = bracket.exposures[0].fwhm
    return band_average(spectrum, bracket.wavelengths, fw, what=what, partial=partial,
                        smooth=smooth)


def _calibrate(bracket, l_ref: np.ndarray, ref_unc: np.ndarray, *, unit: str, method: str,
               region: str, response: Any, per_column: bool, sources: list[dict],
               camera_id: str | None, saturation: float | np.ndarray | None,
               columns: str | None = None, extra: dict | None = None) -> Calibration:
    from mehs.calibration import measure
    from mehs.synthesis.response import ResponseCurve

    rows = _region_rows(region, bracket)   # a bad region is refused before any work
    cols = measure.parse_columns(columns, bracket.shape[1], bracket.source)
    if cols is not None and per_column:
        raise InputError("--columns picks the columns a reference fills for one responsivity "
                         "per band: it needs --no-flat-field (a per-column flat field needs "
                         "every column)")
    nb = bracket.shape[2]
    L = 1 << bracket.bit_depth
    sat = np.broadcast_to(np.asarray(0.98 * (L - 1) if saturation is None else saturation,
                                     dtype=np.float64), (nb,))
    # the calibrated bands first: bands the reference spectra do not cover (--partial) need
    # no signal in the capture (an LED-lit panel is dark in the NIR)
    keep = np.flatnonzero(np.isfinite(l_ref))
    if keep.size == 0:
        raise InputError("the reference spectrum covers none of the camera's bands")
    if np.any(np.diff(keep) != 1):
        raise InputError("the reference spectrum leaves a gap inside the camera's bands")
    l_ref, ref_unc = l_ref[keep], ref_unc[keep]
    zero = l_ref <= 0
    if zero.any():
        k = int(np.flatnonzero(zero)[0])
        raise InputError(f"the reference radiance is zero at {bracket.wavelengths[keep[k]]:.2f} nm "
                         f"({int(zero.sum())} band(s)): it cannot calibrate those bands")
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
        dn, rel = measure.white_dn_per_ms(bracket, curve, sat, keep)
    else:
        dn, rel = measure.frame_dn_per_ms(bracket, curve, rows, sat, keep)
    params: dict[str, Any] = {"region": region, "per_column": per_column}
    if cols is not None:
        dn, rel = dn[cols[0]:cols[1] + 1], rel[cols[0]:cols[1] + 1]
        params["columns"] = [cols[0], cols[1]]
    prof = measure.check_columns_filled(dn, bracket.source)
    # the flat field's range: vignetting and PRNU, and any non-uniformity of the reference
    # across the slit, which a flat field cannot tell from them
    params["column_profile"] = [float(np.min(prof)), float(np.max(prof))]
    if not per_column:
        dn, rel, spread = measure.reduce_columns(dn, rel)
        params["column_spread_median"] = float(np.median(spread))
    resp = dn / l_ref[None, :]
    unc = np.sqrt(rel ** 2 + ref_unc[None, :] ** 2)
    e0 = bracket.exposures[0]
    cam = {"id": camera_id or bracket_camera_id(bracket), "binning": e0.binning,
           "samples": int(bracket.shape[1]), "bit_depth": int(bracket.bit_depth)}
    params.update({"times_ms": bracket.times_ms.tolist(),
                   "reference_band_values": l_ref.tolist(), **(extra or {})})
    return Calibration(resp, unc, bracket.wavelengths, unit, method, fwhm=e0.fwhm, camera=cam,
                       bands=keep,
                       response=resp_info, sources=sources,
                       created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                       parameters=params)


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


def _band_uncertainty(bracket, spec: Spectrum) -> np.ndarray:
    """A spectrum's relative uncertainty column at the band centres (zeros without one)."""
    if spec.uncertainty is None:
        return np.zeros(bracket.wavelengths.size)
    return np.interp(bracket.wavelengths, spec.wavelengths, spec.uncertainty)


def calibrate_panel_relative(bracket, panel: Spectrum, illuminant: Spectrum, *,
                             region: str = "white", response: Any = None, per_column: bool = True,
                             camera_id: str | None = None, partial: bool = False,
                             saturation: float | np.ndarray | None = None,
                             columns: str | None = None) -> Calibration:
    """Relative calibration from a diffuse panel ``ρ(λ)`` under an illuminant of relative SPD ``S(λ)``.

    ``L_ref = ρ·S/π`` per band (band-averaged over the camera's spectral
    response), with ``S`` scaled to a mean of 1 over 400–700 nm (the absolute
    level is unknown, so calibrated data are in :data:`UNIT_RELATIVE`: the true
    radiance times one unknown constant). ``partial``: calibrate the bands the
    spectra cover (a contiguous range) instead of refusing. ``columns`` (``"A-B"``,
    with ``per_column=False``): the columns a panel narrower than the view fills.
    The uncertainty columns of both files are added in quadrature.
    """
    rho = _reference_bands(bracket, panel, "panel reflectance", partial)
    s = _reference_bands(bracket, illuminant, "illuminant SPD", partial)
    vis = (bracket.wavelengths >= 400) & (bracket.wavelengths <= 700)
    vis &= np.isfinite(s)
    norm = s[vis].mean() if vis.any() else np.nanmean(s)
    if not norm > 0:
        raise InputError(f"illuminant ({illuminant.source}) has no power in 400-700 nm")
    l_ref = rho * (s / norm) / np.pi
    unc = np.hypot(_band_uncertainty(bracket, panel), _band_uncertainty(bracket, illuminant))
    sources = _capture_sources(bracket) + [_spec_source("panel", panel),
                                           _spec_source("illuminant", illuminant)]
    return _calibrate(bracket, l_ref, unc, unit=UNIT_RELATIVE, method="panel-relative",
                      region=region, response=response, per_column=per_column, sources=sources,
                      camera_id=camera_id, saturation=saturation, columns=columns,
                      extra={"illuminant_norm_400_700": float(norm)})


def calibrate_source_absolute(bracket, source: Spectrum, *, region: str = "frame",
                              response: Any = None, per_column: bool = True,
                              camera_id: str | None = None, partial: bool = False,
                              saturation: float | np.ndarray | None = None,
                              columns: str | None = None,
                              source_unit: str | None = None) -> Calibration:
    """Absolute calibration from a source of known spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹).

    The certificate's unit is ``source_unit``, else the one its header names
    (W/(cm²·sr·nm), µW…, per µm: converted), else taken as W·sr⁻¹·m⁻²·nm⁻¹ — recorded
    in ``parameters["source_unit"]`` (:mod:`mehs.calibration.units`); an irradiance is
    refused. The certificate is a smooth source: between its points it is interpolated
    as a spline of ``ln L`` unless it has lines (:func:`~mehs.calibration.spectra.band_average`).
    Its relative uncertainty (third column) is propagated. ``partial``: calibrate the
    bands the certificate covers instead of refusing. ``columns``: see
    :func:`calibrate_panel_relative`.
    """
    from dataclasses import replace

    from mehs.calibration.units import source_unit as _unit

    su = _unit(source.header, source_unit, source.source)
    if su["factor"] != 1.0:
        source = replace(source, values=source.values * su["factor"])
    l_ref = _reference_bands(bracket, source, "source radiance", partial, smooth=True)
    unc = _band_uncertainty(bracket, source)
    sources = _capture_sources(bracket) + [_spec_source("source", source)]
    return _calibrate(bracket, l_ref, unc, unit=UNIT_ABSOLUTE, method="source-absolute",
                      region=region, response=response, per_column=per_column, sources=sources,
                      camera_id=camera_id, saturation=saturation, columns=columns,
                      extra={"source_unit": su})
