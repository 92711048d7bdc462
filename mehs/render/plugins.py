"""Mitsuba 3 plugins written in Python: a spectral lat-long environment emitter and a
smooth thin-film reflector.

Mitsuba's own ``envmap`` stores RGB and up-samples it per wavelength (Jakob & Hanika
2019); :class:`HSEnvmap` instead evaluates the measured spectrum of each map pixel at the
path's sampled wavelengths. Mitsuba binds Python subclasses of ``mi.Emitter`` /
``mi.BSDF`` to the variant active when the class statement runs, so the classes are
built per variant by :func:`plugin_classes`.

Both plugins are written for the *scalar* variants (``scalar_spectral``, and
``scalar_rgb`` for the RGB thin-film reflector): Mitsuba calls them once per ray, so the
per-call work is a few numpy look-ups on precomputed tables.

Conventions (shared with Mitsuba's ``envmap`` so RGB and HS renders line up pixel for
pixel): a world direction ``d`` maps to ``u = atan2(d.x, -d.z) / 2π`` (wrapped to [0,1))
and ``v = acos(d.y) / π``; map row 0 is the zenith (``+y``), pixel centres at
``(i + 0.5) / size``, bilinear filtering, wrap-around in ``u``.

References
----------
- Debevec, P. (1998). Rendering synthetic objects into real scenes. SIGGRAPH.
- Pharr, Jakob & Humphreys (2016). Physically Based Rendering, 3rd ed., §14.2.4
  (infinite area light importance sampling: pdf ``p(u,v) / (2π² sin θ)``).
- Jakob, W. & Hanika, J. (2019). A low-dimensional function space for efficient
  spectral upsampling. Computer Graphics Forum 38(2).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from functools import lru_cache

import numpy as np

from mehs.render.maps import EnvMap, map_weights

_TWO_PI_SQ = 2.0 * math.pi * math.pi


def _bilinear_corners(u: float, v: float, h: int, w: int):
    """Corner indices and weights of the bilinear tap at ``(u, v)``, Mitsuba's layout:
    column ``i`` sits at ``u = (i + 0.5) / w`` (wrapping), row ``j`` at ``v = j / (h - 1)``."""
    x = u * w - 0.5
    x0 = math.floor(x)
    fx = x - x0
    x0 %= w
    x1 = (x0 + 1) % w
    y = min(max(v, 0.0), 1.0) * (h - 1)
    y0 = min(int(y), h - 2)
    fy = y - y0
    return y0, y0 + 1, x0, x1, fx, fy


def _lerp_bands(values: list, grid: list, wavelengths, clamp: bool = False) -> list:
    """Values ``(B,)`` on ascending ``grid`` (B,) interpolated at Mitsuba's wavelengths;
    0 outside the grid, or the edge value when ``clamp``."""
    out = []
    last = len(grid) - 1
    for i in range(len(wavelengths)):
        lam = wavelengths[i]
        j = bisect_right(grid, lam) - 1
        if j < 0:
            out.append(values[0] if clamp else 0.0)
        elif j >= last:
            out.append(values[last] if (clamp or lam == grid[last]) else 0.0)
        else:
            t = (lam - grid[j]) / (grid[j + 1] - grid[j])
            out.append(values[j] + t * (values[j + 1] - values[j]))
    return out


def support_wavelengths(wavelengths: np.ndarray) -> np.ndarray:
    """Band centres ``(B,)`` padded by half the edge steps: ``(B + 2,)`` nm."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    return np.concatenate([[wl[0] - (wl[1] - wl[0]) / 2], wl, [wl[-1] + (wl[-1] - wl[-2]) / 2]])


@lru_cache(maxsize=None)
def plugin_classes(variant: str):
    """``(HSEnvmap, ThinFilmBSDF)`` bound to Mitsuba ``variant`` (sets it active)."""
    import mitsuba as mi

    mi.set_variant(variant)
    spectral = mi.is_spectral

    class HSEnvmap(mi.Emitter):
        """Lat-long environment emitter with a spectrum per pixel.

        Constructed from an :class:`~mehs.render.maps.EnvMap` (radiance ``(H, W, B)``
        at ``wavelengths`` (B,) nm, linearly interpolated between bands, 0 outside
        them). Importance sampling draws a cell of an ``H × W`` grid over ``(u, v)`` with
        probability ∝ :func:`~mehs.render.maps.map_weights` and a uniform point inside
        it; the pdf is ``p_cell · W·H / (2π² sin θ)``.
        """

        def __init__(self, props, envmap: EnvMap | None = None, scale: float = 1.0):
            super().__init__(props)
            if envmap is None:
                raise ValueError("HSEnvmap needs an EnvMap (construct it from Python)")
            self.m_flags = mi.EmitterFlags.Infinite | mi.EmitterFlags.SpatiallyVarying
            data = np.asarray(envmap.radiance, dtype=np.float64) * float(scale)
            # each band stands for the half-way interval to its neighbours, so the edge
            # bands hold their value half a band step outwards (400 nm covers 395–405)
            self._wl = support_wavelengths(envmap.wavelengths)
            data = np.concatenate([data[..., :1], data, data[..., -1:]], axis=-1)
            self._data = np.ascontiguousarray(data)
            self._flat = self._data.reshape(-1, data.shape[-1])
            self._wl_list = self._wl.tolist()
            self._h, self._w = data.shape[:2]
            w = map_weights(envmap).reshape(-1)
            cdf = np.cumsum(w)
            self._total = float(cdf[-1])
            # Python lists: Mitsuba calls these per ray, where numpy's per-call overhead
            # would dominate
            self._cdf = cdf.tolist()
            self._pmf = (w / self._total).tolist()
            self._radius = 1.0
            self._center = mi.Point3f(0.0)

        # -- scene ---------------------------------------------------------
        def set_scene(self, scene):
            # Mitsuba does not call this on Python emitters: whoever loads the scene must
            # (mehs.render.scene does), or shadow rays end 2 units out
            bbox = scene.bbox()
            if bbox.valid():
                sph = bbox.bounding_sphere()
                self._center = sph.center
                self._radius = max(float(sph.radius), 1e-3)

        def bbox(self):
            return mi.ScalarBoundingBox3f()

        # -- evaluation ----------------------------------------------------
        def _value(self, u: float, v: float, wavelengths) -> "mi.Spectrum":
            y0, y1, x0, x1, fx, fy = _bilinear_corners(u, v, self._h, self._w)
            w = self._w
            rows = self._flat[[y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1]]
            spec = np.array([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]) @ rows
            return mi.Spectrum(*_lerp_bands(spec.tolist(), self._wl_list, wavelengths))

        @staticmethod
        def _uv(d) -> tuple[float, float]:
            x, y, z = float(d[0]), float(d[1]), float(d[2])
            u = math.atan2(x, -z) / (2.0 * math.pi)
            u -= math.floor(u)
            v = math.acos(min(max(y, -1.0), 1.0)) / math.pi
            return u, v

        def eval(self, si, active=True):
            u, v = self._uv(-si.wi)
            return self._value(u, v, si.wavelengths)

        def eval_direction(self, it, ds, active=True):
            u, v = self._uv(ds.d)
            return self._value(u, v, it.wavelengths)

        def _pdf_uv(self, u: float, v: float) -> float:
            sin_t = math.sin(v * math.pi)
            if sin_t <= 0.0:
                return 0.0
            px = min(int(u * self._w), self._w - 1)
            py = min(int(v * self._h), self._h - 1)
            return self._pmf[py * self._w + px] * self._w * self._h / (_TWO_PI_SQ * sin_t)

        def sample_direction(self, it, sample, active=True):
            s0, s1 = float(sample[0]), float(sample[1])
            t = s0 * self._total
            idx = min(bisect_right(self._cdf, t), len(self._cdf) - 1)
            lo = self._cdf[idx - 1] if idx > 0 else 0.0
            wgt = self._cdf[idx] - lo
            fu = (t - lo) / wgt if wgt > 0 else 0.5
            fu = min(max(fu, 0.0), 1.0 - 1e-7)
            py, px = divmod(idx, self._w)
            u = (px + fu) / self._w
            v = (py + s1) / self._h
            theta, phi = v * math.pi, u * 2.0 * math.pi
            st = math.sin(theta)
            d = mi.Vector3f(st * math.sin(phi), math.cos(theta), -st * math.cos(phi))
            pdf = self._pdf_uv(u, v)
            ds = mi.DirectionSample3f()
            ds.p = it.p + d * (2.0 * self._radius)
            ds.n = -d
            ds.uv = mi.Point2f(u, v)
            ds.time = it.time
            ds.pdf = pdf
            ds.delta = False
            ds.emitter = self
            ds.d = d
            ds.dist = float("inf")
            if pdf <= 0.0:
                return ds, mi.Spectrum(0.0)
            return ds, self._value(u, v, it.wavelengths) / pdf

        def pdf_direction(self, it, ds, active=True):
            u, v = self._uv(ds.d)
            return self._pdf_uv(u, v)

        def sample_wavelengths(self, si, sample, active=True):
            # uniform over the map's band range (only light tracing asks for it)
            lo, hi = float(self._wl[0]), float(self._wl[-1])
            n = len(si.wavelengths) if spectral else 0
            if not spectral:
                return mi.Spectrum(0.0), mi.Spectrum(1.0)
            lam = [lo + (hi - lo) * ((float(sample) + i / n) % 1.0) for i in range(n)]
            return mi.Spectrum(*lam), mi.Spectrum(hi - lo)

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            raise NotImplementedError("HSEnvmap supports path tracing (camera rays) only")

        def sample_position(self, ref, ds, active=True):
            raise NotImplementedError("HSEnvmap has no position sampling")

        def pdf_position(self, ps, active=True):
            return 0.0

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"HSEnvmap[{self._h}x{self._w}, {self._wl.size} bands]"

    class ThinFilmBSDF(mi.BSDF):
        """A smooth mirror with angle- and wavelength-dependent reflectance.

        ``reflectance`` is tabulated on ``cos_theta`` (C,) ascending in [0, 1] and, in
        spectral variants, ``wavelengths`` (L,) nm: an array ``(L, C)``; in RGB
        variants ``(3, C)`` (linear sRGB). Look-ups are linear in both.
        """

        def __init__(self, props, table: np.ndarray | None = None,
                     cos_theta: np.ndarray | None = None,
                     wavelengths: np.ndarray | None = None):
            super().__init__(props)
            if table is None or cos_theta is None:
                raise ValueError("ThinFilmBSDF needs a reflectance table")
            self._table = np.asarray(table, dtype=np.float64)
            self._cos = np.asarray(cos_theta, dtype=np.float64)
            self._wl = None if wavelengths is None else np.asarray(wavelengths, np.float64)
            self._wl_list = None if self._wl is None else self._wl.tolist()
            self._nc = self._cos.size
            self.m_flags = mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.FrontSide
            self.m_components = [self.m_flags]

        def _reflectance(self, cos_i: float, wavelengths):
            x = cos_i * (self._nc - 1)
            i0 = min(int(x), self._nc - 2)
            f = x - i0
            if self._wl is None:
                t = self._table
                return mi.Spectrum(*[(1 - f) * t[c, i0] + f * t[c, i0 + 1] for c in range(3)])
            col = ((1 - f) * self._table[:, i0] + f * self._table[:, i0 + 1]).tolist()
            return mi.Spectrum(*_lerp_bands(col, self._wl_list, wavelengths, clamp=True))

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            cos_i = float(mi.Frame3f.cos_theta(si.wi))
            if cos_i <= 0.0 or not ctx.is_enabled(mi.BSDFFlags.DeltaReflection, 0):
                return bs, mi.Spectrum(0.0)
            bs.wo = mi.reflect(si.wi)
            bs.pdf = 1.0
            bs.eta = 1.0
            bs.sampled_type = int(mi.BSDFFlags.DeltaReflection)
            bs.sampled_component = 0
            return bs, self._reflectance(min(cos_i, 1.0), si.wavelengths)

        def eval(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return 0.0

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0), 0.0

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"ThinFilmBSDF[{self._table.shape}]"

    return HSEnvmap, ThinFilmBSDF
