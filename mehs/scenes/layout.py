"""Spatial structure of a natural scene: occluding regions, shading, shadows, texture fields.

The layout is a *dead-leaves* model (Matheron 1968; Lee, Mumford & Huang 2001): shapes of
power-law distributed size (p(r) ∝ r⁻³, scale invariant, which gives natural images their 1/f²
power spectrum) are painted one over the other, so regions have varied size and shape, sharp
occluding edges and T-junctions. Shapes are ellipses (rounded objects, with a normal field for
shading and highlights), rotated rectangles (planar surfaces with a shading gradient) and
irregular blobs (foliage, stones: an ellipse with a harmonic radius). Each rounded object and
rectangle casts a shadow: its mask shifted along the light direction darkens the surfaces
*behind* it (painted earlier), with a blurred penumbra.

Texture fields are 1/f^β Gaussian noise (β = 1.5–2.2, Field 1987), synthesised by FFT.

References
----------
- Lee, Mumford & Huang (2001), "Occlusion models for natural images: a statistical study of a
  scale-invariant dead leaves model", IJCV 41(1/2) 35–59.
- Field (1987), "Relations between the statistics of natural images and the response
  properties of cortical cells", JOSA A 4(12).
- Blinn (1977), "Models of light reflection for computer synthesized pictures", SIGGRAPH.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Shape kinds of the dead-leaves layout.
SHAPES = ("ellipse", "rectangle", "blob")


@dataclass
class Layout:
    """Per-pixel fields of a scene layout; all ``(lines, samples)``.

    Attributes
    ----------
    label
        int32 region index (0 = the background plane).
    lambert
        float32 cosine factor of the direct light, in [0, 1].
    specular
        float32 Blinn–Phong highlight weight (neutral interface reflection).
    shadow
        float32 in [0, 1]: fraction of the direct light blocked (soft-edged).
    n_regions
        Number of region indices (painted shapes + the background).
    kinds
        ``(n_regions,)`` shape kind index into :data:`SHAPES` (−1 for the background).
    """

    label: np.ndarray
    lambert: np.ndarray
    specular: np.ndarray
    shadow: np.ndarray
    n_regions: int
    kinds: np.ndarray


def noise_field(rng: np.random.Generator, shape: tuple[int, int], beta: float = 2.0) -> np.ndarray:
    """Gaussian 1/f^β noise, zero mean, unit std; float32 ``shape``."""
    h, w = shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2.0)
    amp[0, 0] = 0.0
    spec = amp * (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape))
    n = np.fft.irfft2(spec, s=(h, w))
    s = n.std()
    return (n / s if s > 0 else n).astype(np.float32)


def _shape_mask(kind: str, yy: np.ndarray, xx: np.ndarray, r: float, aspect: float,
                theta: float, harmonics: np.ndarray):
    """Mask and local coordinates (u, v in units of the half axes) of one shape in its box."""
    c, s = np.cos(theta), np.sin(theta)
    u = (c * xx + s * yy) / r
    v = (-s * xx + c * yy) / (r * aspect)
    if kind == "rectangle":
        return (np.abs(u) <= 1) & (np.abs(v) <= 1), u, v
    rho = np.sqrt(u * u + v * v)
    if kind == "blob":
        phi = np.arctan2(v, u)
        k = np.arange(1, harmonics.shape[0] + 1)[:, None, None]
        wob = (harmonics[:, 0, None, None] * np.sin(k * phi + harmonics[:, 1, None, None])).sum(0)
        return rho <= 1.0 + wob, u, v
    return rho <= 1.0, u, v


def make_layout(rng: np.random.Generator, lines: int, samples: int, *,
                light_dir: tuple[float, float, float], shadow_length: float,
                density: float = 1.0, gloss_fraction: float = 0.35) -> Layout:
    """Paint a dead-leaves layout.

    Parameters
    ----------
    light_dir
        Unit vector (x right, y down, z towards the viewer) pointing at the direct light.
    shadow_length
        Shadow offset per unit of object size (0 = no cast shadows).
    density
        Shapes per 100 pixels of area (scaled; ≈ 650 shapes at 256×256 for 1.0).
    gloss_fraction
        Fraction of rounded objects that are glossy (get a specular highlight).
    """
    size = float(min(lines, samples))
    n_shapes = max(8, int(round(density * lines * samples / 100.0)))
    r_min, r_max = max(1.2, 0.008 * size), 0.45 * size
    # p(r) ∝ r^-3 on [r_min, r_max], by inverse CDF
    q = rng.uniform(size=n_shapes)
    radii = 1.0 / np.sqrt(r_min ** -2 - q * (r_min ** -2 - r_max ** -2))
    # big shapes first (background structure), then sizes shuffled: a natural occlusion order
    order = np.argsort(-radii + rng.uniform(0, 0.5 * size, n_shapes) * (radii < 0.1 * size))
    radii = radii[order]
    kinds = rng.choice(len(SHAPES), size=n_shapes, p=(0.45, 0.25, 0.30))
    label = np.zeros((lines, samples), dtype=np.int32)
    lam = np.full((lines, samples), 0.9, dtype=np.float32)
    spec = np.zeros((lines, samples), dtype=np.float32)
    lx, ly, lz = light_dir
    # the background is a plane tilted towards the light, brighter at the bottom (ground)
    vv = np.linspace(0.0, 1.0, lines, dtype=np.float32)[:, None]
    lam[:] = np.clip(0.55 + 0.4 * vv * lz, 0.05, 1.0)
    hx, hy, hz = lx, ly, lz + 1.0
    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    boxes = []
    for k in range(n_shapes):
        r = float(radii[k])
        aspect = float(rng.uniform(0.35, 1.0))
        theta = float(rng.uniform(0, np.pi))
        cy, cx = rng.uniform(-0.1, 1.1) * lines, rng.uniform(-0.1, 1.1) * samples
        kind = SHAPES[kinds[k]]
        harm = np.stack([rng.uniform(0, 0.12, 4) / np.arange(1, 5), rng.uniform(0, 2 * np.pi, 4)], 1)
        ext = r * 1.5 + 1
        y0, y1 = max(0, int(cy - ext)), min(lines, int(cy + ext) + 1)
        x0, x1 = max(0, int(cx - ext)), min(samples, int(cx + ext) + 1)
        if y0 >= y1 or x0 >= x1:
            boxes.append(None)
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        m, u, v = _shape_mask(kind, yy - cy, xx - cx, r, aspect, theta, harm)
        if not m.any():
            boxes.append(None)
            continue
        idx = k + 1
        label[y0:y1, x0:x1][m] = idx
        if kind == "rectangle":
            # a planar facet: its own orientation, shading varying linearly across it
            nx, ny = rng.normal(0, 0.45, 2)
            nz = 1.0
            nrm = np.sqrt(nx * nx + ny * ny + nz * nz)
            base = max(0.05, (nx * lx + ny * ly + nz * lz) / nrm)
            grad = rng.normal(0, 0.15) * u + rng.normal(0, 0.15) * v
            lam[y0:y1, x0:x1][m] = np.clip(base + grad, 0.03, 1.0)[m]
        else:
            # a rounded object: normals of an ellipsoid (blobs are flatter, less shiny)
            c, s = np.cos(theta), np.sin(theta)
            rho2 = np.clip(u * u + v * v, 0, 0.999)
            bulge = 1.0 if kind == "ellipse" else 0.5
            ux, uy = c * u - s * v, s * u + c * v  # back to image axes
            nz = np.sqrt(1.0 - rho2) + (1 - bulge)
            nrm = np.sqrt(ux * ux + uy * uy + nz * nz)
            nx_, ny_, nz_ = ux / nrm, uy / nrm, nz / nrm
            lam[y0:y1, x0:x1][m] = np.clip(nx_ * lx + ny_ * ly + nz_ * lz, 0.02, 1.0)[m]
            if rng.uniform() < gloss_fraction * (1.0 if kind == "ellipse" else 0.4):
                p = float(rng.uniform(15, 120))
                ks = float(rng.uniform(0.05, 0.6))
                hl = np.clip(nx_ * hx + ny_ * hy + nz_ * hz, 0, 1) ** p * ks
                spec[y0:y1, x0:x1][m] = hl[m]
            else:
                spec[y0:y1, x0:x1][m] = 0.0
        boxes.append((y0, y1, x0, x1, m, r))
    shadow = _cast_shadows(label, boxes, light_dir, shadow_length)
    return Layout(label=label, lambert=lam, specular=spec, shadow=shadow,
                  n_regions=n_shapes + 1, kinds=np.concatenate([[-1], kinds]).astype(np.int32))


def _cast_shadows(label: np.ndarray, boxes: list, light_dir, shadow_length: float) -> np.ndarray:
    """Soft shadow map: each shape darkens the pixels of shapes painted before it."""
    from scipy.ndimage import gaussian_filter

    lines, samples = label.shape
    shadow = np.zeros((lines, samples), dtype=np.float32)
    if shadow_length <= 0:
        return shadow
    lx, ly, lz = light_dir
    planar = np.hypot(lx, ly)
    if planar < 1e-6:
        return shadow
    # the shadow falls away from the light, longer for a low light
    dx, dy = -lx / planar, -ly / planar
    for k, box in enumerate(boxes):
        if box is None:
            continue
        y0, y1, x0, x1, m, r = box
        off = shadow_length * r * planar / max(lz, 0.15)
        sy, sx = int(round(dy * off)), int(round(dx * off))
        ty0, ty1, tx0, tx1 = y0 + sy, y1 + sy, x0 + sx, x1 + sx
        cy0, cy1, cx0, cx1 = max(ty0, 0), min(ty1, lines), max(tx0, 0), min(tx1, samples)
        if cy0 >= cy1 or cx0 >= cx1:
            continue
        mm = m[cy0 - ty0:cy1 - ty0, cx0 - tx0:cx1 - tx0]
        behind = label[cy0:cy1, cx0:cx1] < k + 1
        shadow[cy0:cy1, cx0:cx1][mm & behind] = 1.0
    sigma = max(0.6, 0.004 * min(lines, samples))
    return np.clip(gaussian_filter(shadow, sigma), 0.0, 1.0).astype(np.float32)
