"""How diverse are the spectra of a set of scenes (``spectral_diversity``)?

Figures, all on spectra normalised to unit L2 norm (so brightness and shading do not count):

- ``distinct_spectra``: leader clustering (Hartigan 1975) of up to ``sample`` pixels at
  ``angle_deg``: a pixel starts a new cluster when it is more than ``angle_deg`` from every
  existing leader. A ColorChecker scene gives about its patch count, a natural scene thousands.
- ``pcs_90`` / ``pcs_99``: principal components (of the mean-centred normalised spectra) needed
  to explain 90 % / 99 % of the variance.
- ``nn_angle_median`` / ``nn_angle_p90`` (with ``reference``): the angle (degrees) from each
  sampled pixel to its nearest reference (training) pixel: how far a test scene lies outside
  what a model was trained on.

The pixels are drawn at random from all the cubes (a raster-order prefix would describe the
top lines, or the first scenes, only).

Noise
-----
The direction of a spectrum buried in noise is the noise's: a fused (signed) HDR cube of a
ColorChecker (48², 1°) at 10⁻³ of its light gave 2304 "distinct spectra" in 2304 pixels (truth: 24)
and pixel-to-training angles of 80° (truth: under 1°); clipping the negatives does not help.
So pixels whose spectrum is not resolved above the noise are excluded, and counted.

The noise is measured from the cube itself, pixel by pixel (:func:`noise_angles`): the
spatial second difference of neighbouring unit spectra (``u₋ + u₊ − 2u``; shading and texture
change the norm, not the direction, and a smooth change across the image cancels), high-passed
across bands (an edge between two materials is smooth in wavelength), gives the per-band noise
and so the angle ``α`` it turns the spectrum by; along and across the line, the smaller. Each
pixel then takes the median ``α`` of the :data:`NOISE_WINDOW` pixels nearest to it in
brightness — noise is a function of the signal (read, shot, the exposures an HDR merge used),
texture is not. A pixel is kept when ``α ≤ noise_angle_deg`` (default ``angle_deg / 2``: two
pixels of one material then lie ≈ 0.7·``angle_deg`` apart and join one cluster). Against the
simulator's true radiance (48² ColorChecker with its lamp, 31 bands, light 1 … 10⁻³) pixels
estimated at 0.25–0.5° lie 0.50–0.55° (median) from the truth, at 1–2° 1.4–1.7°: about 20 %
low. A noise-free 256² natural scene loses 0.05 % of its pixels.

What it cannot tell: spectra that really change from pixel to pixel look like noise (a
random material per pixel; noise-free 24² natural scenes, whose regions and lamp glows span a
few pixels, lose 0–30 %); noise correlated between neighbours (a demosaiced or resampled
cube) is underestimated; pixels saturated in every exposure are identical neighbours —
pass the fused cube's mask as ``valid``. ``min_norm`` (cube units) replaces the test by a
threshold on ``‖x‖`` (``0`` keeps every pixel). Rows without a spatial layout (``(N, B)``)
cannot be measured: they are used whole and recorded as ``not measured``.

References
----------
- Hartigan (1975), *Clustering Algorithms*, Wiley (the leader algorithm).
- Chakrabarti & Zickler (2011), "Statistics of real-world hyperspectral images", CVPR.
- Kruse et al. (1993), "The spectral image processing system (SIPS)", Remote Sens. Environ.
  44 (the spectral angle).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from mehs.errors import InputError

#: Pixels clustered (the leader algorithm costs N × clusters).
LEADER_MAX = 8192
#: Pixels whose nearest reference pixel is searched.
NEAREST_MAX = 4000
#: Pixels (nearest in brightness) whose median noise angle a pixel is given.
NOISE_WINDOW = 31
#: Bands from which the noise angle counts only the band-to-band part of a difference.
NOISE_HP_BANDS = 8


def unit_spectra(cubes: np.ndarray | Iterable[np.ndarray], *, sample: int | None = None,
                 seed: int = 0) -> np.ndarray:
    """Pixels of one or more ``(..., B)`` arrays as unit-norm float64 rows ``(N, B)``.

    Zero-norm and non-finite pixels are dropped; ``sample`` draws that many rows at random.
    No noise screening: see :func:`screen_cube`.
    """
    arrays = _arrays(cubes)
    b = arrays[0].shape[-1]
    x = np.concatenate([np.asarray(a, dtype=np.float64).reshape(-1, b) for a in arrays])
    ok = np.all(np.isfinite(x), axis=1)
    x = x[ok]
    n = np.linalg.norm(x, axis=1)
    x = x[n > 0] / n[n > 0, None]
    if x.shape[0] == 0:
        raise InputError("no pixel has a non-zero spectrum")
    if sample is not None and x.shape[0] > sample:
        x = x[np.random.default_rng(seed).choice(x.shape[0], sample, replace=False)]
    return x


def _arrays(cubes, what: str = "spectra") -> list[np.ndarray]:
    arrays = [cubes] if isinstance(cubes, np.ndarray) else list(cubes)
    if not arrays:
        raise InputError(f"no {what} given")
    arrays = [a if isinstance(a, np.ndarray) else np.asarray(a) for a in arrays]
    if any(a.ndim < 1 or a.shape[-1] < 1 for a in arrays):
        raise InputError(f"{what}: every array must be (..., bands) with at least one band")
    bands = {a.shape[-1] for a in arrays}
    if len(bands) != 1:
        raise InputError(f"the cubes have different band counts {sorted(bands)}")
    return arrays


# ----------------------------------------------------------------------------- noise
def _unit_lines(cube: np.ndarray, rows: slice, valid: np.ndarray | None) -> np.ndarray:
    """Lines ``rows`` of ``cube`` as unit float64 spectra ``(R, W, B)``; NaN where unusable."""
    x = np.asarray(cube[rows], dtype=np.float64)
    n = np.sqrt(np.einsum("...b,...b->...", x, x))
    bad = ~(np.isfinite(n) & (n > 0))
    if valid is not None:
        bad |= ~valid[rows]
    n[bad] = np.nan
    return x / n[..., None]


def _noise_var(h: np.ndarray) -> np.ndarray:
    """Per-band noise variance ``s²`` of unit spectra from their spatial second differences
    ``h = u₋ + u₊ − 2u (..., B)`` (variance 6·s² for white noise).

    From :data:`NOISE_HP_BANDS` bands on, only the part that changes from band to band
    counts: ``g_b = h_b − (h_{b−1} + h_{b+1})/2`` has variance 1.5 × 6·s², while the
    difference between two materials (an edge) is smooth over three bands and leaves ``g``
    near 0. The spatial second difference already cancels what changes smoothly across
    the image (a light's fall-off, a blend of materials).
    """
    b = h.shape[-1]
    if b < NOISE_HP_BANDS:
        return np.einsum("...b,...b->...", h, h) / (6.0 * b)
    g = h[..., 1:-1] - 0.5 * (h[..., :-2] + h[..., 2:])
    return np.einsum("...b,...b->...", g, g) / (9.0 * (b - 2))


def noise_angles(cube: np.ndarray, valid: np.ndarray | None = None, *,
                 block: int = 64) -> np.ndarray:
    """Angular noise ``α`` (degrees) of each pixel of ``cube (H, W, B)``, float64 ``(H, W)``.

    ``α = s·√(B−1)`` (the angle white noise of ``s²`` a band turns a unit spectrum by), ``s²``
    by :func:`_noise_var` along the line and across it, the smaller of the two (one of them
    may cross an edge). NaN where the pixel or both pairs of neighbours are unusable
    (non-finite, zero, outside ``valid``, the image's corners). ``block`` lines at a time.
    """
    h, w, b = cube.shape
    v = None if valid is None else np.asarray(valid, dtype=bool).reshape(h, w)
    out = np.empty((h, w))
    for r0 in range(0, h, block):
        r1 = min(h, r0 + block)
        lo, hi = max(0, r0 - 1), min(h, r1 + 1)
        u = _unit_lines(cube, slice(lo, hi), v)                 # lines lo … hi−1
        c = u[r0 - lo:r1 - lo]                                   # the block's own lines
        sx = np.full(c.shape[:2], np.nan)
        sy = np.full(c.shape[:2], np.nan)
        if w >= 3:
            sx[:, 1:-1] = _noise_var(c[:, :-2] + c[:, 2:] - 2.0 * c[:, 1:-1])
        i = np.arange(r0, r1)
        inner = (i > 0) & (i < h - 1)
        if inner.any():
            j = i[inner] - lo
            sy[inner] = _noise_var(u[j - 1] + u[j + 1] - 2.0 * u[j])
        with np.errstate(all="ignore"):
            s2 = np.fmin(sx, sy)                                 # NaN only where both are
        out[r0:r1] = np.degrees(np.sqrt(s2 * (b - 1)))
    return out


def by_brightness(alpha: np.ndarray, norm: np.ndarray, ok: np.ndarray, *,
                  window: int = NOISE_WINDOW, chunk: int = 1 << 16) -> np.ndarray:
    """Each ``ok`` pixel's noise angle as the median ``alpha`` of the ``window`` pixels
    nearest to it in brightness (``norm``); NaN elsewhere.

    Noise is a function of the signal (read and shot noise, the exposures an HDR merge
    used); a spectrum that changes between neighbours (an edge, a lamp's glow over a
    patch) is not, and would pass for noise pixel by pixel.
    """
    out = np.full(alpha.shape, np.nan)
    idx = np.flatnonzero(ok)
    if not idx.size:
        return out
    idx = idx[np.argsort(norm[idx], kind="stable")]
    a = alpha[idx]
    w = int(min(window, a.size)) | 1        # odd, centred
    h = w // 2
    # the ends reuse the first / last full window (edge padding would over-weight them)
    pad = np.concatenate([np.full(h, np.nan), a, np.full(h, np.nan)])
    med = np.empty(a.size)
    with np.errstate(all="ignore"):
        for s in range(0, a.size, chunk):
            e = min(a.size, s + chunk)
            win = np.lib.stride_tricks.sliding_window_view(pad[s:e + 2 * h], w)
            med[s:e] = np.nanmedian(win, axis=1) if np.isnan(win).any() else np.median(win, axis=1)
    out[idx] = med
    return out


def _norms(flat: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """float64 L2 norm of each row of ``(N, B)`` (NaN where a value is not finite), by blocks."""
    out = np.empty(flat.shape[0])
    for s in range(0, flat.shape[0], block):
        x = np.asarray(flat[s:s + block], dtype=np.float64)
        out[s:s + block] = np.sqrt(np.einsum("ij,ij->i", x, x))
    return out


def screen_cube(cube: np.ndarray, *, valid: np.ndarray | None = None,
                min_norm: float | None = None, noise_angle_deg: float = 0.5
                ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Which pixels of ``cube (..., B)`` are resolved above the noise.

    Returns the pixels as rows ``(N, B)`` (a view where possible), the boolean ``keep (N,)``
    and the record ``{"pixels", "invalid", "unresolved", "noise_source",
    "noise_angle_median", "min_norm"}``: ``invalid`` counts non-finite, zero and masked
    pixels, ``unresolved`` those whose angular noise (:func:`noise_angles`) is above
    ``noise_angle_deg`` or cannot be measured (no usable neighbour) — or, with ``min_norm``,
    whose norm is below it; ``noise_angle_median`` (degrees) the median over valid pixels.
    """
    cube = np.asarray(cube) if not isinstance(cube, np.ndarray) else cube
    b = cube.shape[-1]
    flat = cube.reshape(-1, b)
    norm = _norms(flat)
    ok = np.isfinite(norm) & (norm > 0)
    v = None
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        if v.size != flat.shape[0]:
            raise InputError(f"a mask of {v.size} pixels for a cube of {flat.shape[0]}")
        ok &= v.reshape(-1)
    rec = {"pixels": int(flat.shape[0]), "invalid": int(flat.shape[0] - ok.sum()),
           "noise_angle_median": None, "min_norm": None}
    if min_norm is not None:
        if not (np.isfinite(min_norm) and min_norm >= 0):
            raise InputError(f"min_norm must be finite and >= 0, got {min_norm}")
        keep = ok & (norm >= min_norm)
        rec.update(noise_source="given: min_norm", min_norm=float(min_norm))
    elif cube.ndim == 3 and max(cube.shape[:2]) >= 3:
        alpha = by_brightness(noise_angles(cube, v).reshape(-1), norm, ok)
        keep = ok & (alpha <= noise_angle_deg)      # NaN (unmeasurable) is not kept
        rec["noise_source"] = "neighbours"
        if np.isfinite(alpha[ok]).any():
            rec["noise_angle_median"] = float(np.nanmedian(alpha[ok]))
    else:
        keep = ok
        rec["noise_source"] = ("not measured: no spatial layout (pixel rows)" if cube.ndim != 3
                               else "not measured: fewer than 3 pixels a side")
    rec["unresolved"] = int(ok.sum() - keep.sum())
    return flat, keep, rec


def merge_records(records: list[dict], prefix: str = "") -> dict:
    """Totals of :func:`screen_cube` records: pixels, exclusions, thresholds per cube."""
    tot = sum(r["pixels"] for r in records)
    inv = sum(r["invalid"] for r in records)
    unres = sum(r["unresolved"] for r in records)
    return {f"{prefix}pixels_total": tot, f"{prefix}excluded_invalid": inv,
            f"{prefix}excluded_noise": unres,
            f"{prefix}excluded_noise_fraction": unres / max(1, tot),
            f"{prefix}noise_angle_median": [r["noise_angle_median"] for r in records],
            f"{prefix}noise_source": [r["noise_source"] for r in records]}


def draw(screened: list[tuple[np.ndarray, np.ndarray]], sample: int | None,
         rng: np.random.Generator) -> np.ndarray:
    """Up to ``sample`` kept rows of all ``(rows, keep)`` pairs, at random, unit-norm float64
    ``(N, B)`` in random order (so a prefix is a random subset too)."""
    idx = [np.flatnonzero(k) for _, k in screened]
    counts = np.array([i.size for i in idx])
    total = int(counts.sum())
    b = screened[0][0].shape[1]
    if total == 0:
        return np.empty((0, b))
    pick = np.arange(total) if sample is None or total <= sample else \
        np.sort(rng.choice(total, int(sample), replace=False))
    starts = np.concatenate([[0], np.cumsum(counts)])
    parts = []
    for (flat, _), ii, s, e in zip(screened, idx, starts[:-1], starts[1:]):
        sel = pick[(pick >= s) & (pick < e)] - s
        if sel.size:
            parts.append(np.asarray(flat[ii[sel]], dtype=np.float64))
    x = np.concatenate(parts)
    x /= np.linalg.norm(x, axis=1)[:, None]
    return x[rng.permutation(x.shape[0])]


# ----------------------------------------------------------------------------- figures
def leader_clusters(x: np.ndarray, angle_deg: float = 1.0, *, batch: int = 1024) -> int:
    """Number of leader clusters of unit rows ``x (N, B)`` at ``angle_deg``."""
    cos_t = np.cos(np.deg2rad(angle_deg))
    leaders = np.empty((0, x.shape[1]))
    for s in range(0, x.shape[0], batch):
        blk = x[s:s + batch]
        if leaders.shape[0]:
            blk = blk[(blk @ leaders.T).max(axis=1) < cos_t]
        if not blk.shape[0]:
            continue
        # greedy within the block, on its own similarity matrix
        sim = blk @ blk.T
        free = np.ones(blk.shape[0], dtype=bool)
        new = []
        for i in range(blk.shape[0]):
            if free[i]:
                new.append(i)
                free &= sim[i] < cos_t
        leaders = np.vstack([leaders, blk[new]])
    return int(leaders.shape[0])


def pcs_for(x: np.ndarray, fractions=(0.9, 0.99)) -> list[int]:
    """Components of the centred rows ``x`` needed for each variance fraction."""
    xc = x - x.mean(axis=0)
    ev = np.linalg.svd(xc, compute_uv=False) ** 2
    tot = ev.sum()
    if not tot > 0:
        return [0 for _ in fractions]
    cum = np.cumsum(ev) / tot
    return [int(np.searchsorted(cum, f - 1e-12) + 1) for f in fractions]


def nearest_angles(x: np.ndarray, ref: np.ndarray, *, batch: int = 2048) -> np.ndarray:
    """Angle (degrees) from each row of ``x`` to its nearest row of ``ref`` (both unit)."""
    out = np.empty(x.shape[0])
    for s in range(0, x.shape[0], batch):
        c = np.clip((x[s:s + batch] @ ref.T).max(axis=1), -1.0, 1.0)
        out[s:s + batch] = np.degrees(np.arccos(c))
    return out


def figures(x: np.ndarray, ref: np.ndarray | None, angle_deg: float) -> dict:
    """The diversity figures of unit rows ``x`` (random order), ``ref`` for the angles.

    With no pixel left (all below the noise) the figures are ``None``, not an error: the
    record says why.
    """
    out = {"pixels": int(x.shape[0]), "bands": int(x.shape[1]), "angle_deg": float(angle_deg)}
    if x.shape[0]:
        p90, p99 = pcs_for(x)
        out.update(distinct_spectra=leader_clusters(x[:LEADER_MAX], angle_deg),
                   pcs_90=p90, pcs_99=p99)
    else:
        out.update(distinct_spectra=None, pcs_90=None, pcs_99=None)
    if ref is not None:
        if ref.shape[1] != x.shape[1]:
            raise InputError(f"reference has {ref.shape[1]} bands, the cubes {x.shape[1]}")
        out["reference_pixels"] = int(ref.shape[0])
        if x.shape[0] and ref.shape[0]:
            a = nearest_angles(x[:NEAREST_MAX], ref)
            out["nn_angle_median"] = float(np.median(a))
            out["nn_angle_p90"] = float(np.percentile(a, 90))
        else:
            out["nn_angle_median"] = out["nn_angle_p90"] = None
    return out


def noise_angle_for(angle_deg: float, noise_angle_deg: float | None) -> float:
    """The noise-angle threshold (degrees): ``noise_angle_deg``, default ``angle_deg / 2``;
    both checked."""
    if not (np.isfinite(angle_deg) and 0 < angle_deg < 180):
        raise InputError(f"angle_deg must be in (0, 180) degrees, got {angle_deg}")
    na = angle_deg / 2 if noise_angle_deg is None else float(noise_angle_deg)
    if not (np.isfinite(na) and 0 < na < 90):
        raise InputError(f"noise_angle_deg must be in (0, 90) degrees, got {noise_angle_deg}")
    return na


def spectral_diversity(cubes, reference=None, *, sample: int = 20000, angle_deg: float = 1.0,
                       seed: int = 0, min_norm: float | None = None,
                       noise_angle_deg: float | None = None, valid=None) -> dict:
    """Diversity figures of ``cubes`` (one ``(H, W, B)`` array or several), see module notes.

    ``valid``: one boolean ``(H, W)`` mask per cube (True: use the pixel), e.g. a fused
    cube's ``mask == 0`` — pixels saturated in every exposure are consistent between
    neighbours, so the noise test keeps them although their spectra are clipped.

    ``reference``: training cubes for the nearest-training-pixel angle (optional).
    ``noise_angle_deg`` (default ``angle_deg / 2``): the largest angular noise a kept pixel
    may have; ``min_norm``: a threshold on ``‖x‖`` instead of the measured noise (``0``
    keeps every pixel). Besides the figures: ``noise_angle_deg`` (the threshold used),
    ``pixels_total``, ``excluded_invalid``, ``excluded_noise`` and
    ``excluded_noise_fraction``, per cube ``noise_angle_median`` and ``noise_source``, and
    the same with a ``reference_`` prefix.
    """
    na = noise_angle_for(angle_deg, noise_angle_deg)
    rng = np.random.default_rng(seed)
    arrays = _arrays(cubes)
    masks = [None] * len(arrays) if valid is None else \
        [valid] if isinstance(valid, np.ndarray) and len(arrays) == 1 else list(valid)
    if len(masks) != len(arrays):
        raise InputError(f"{len(masks)} masks for {len(arrays)} cubes")
    scr = [screen_cube(a, valid=m, min_norm=min_norm, noise_angle_deg=na)
           for a, m in zip(arrays, masks)]
    rec = merge_records([r for _, _, r in scr])
    if rec["pixels_total"] == rec["excluded_invalid"]:
        raise InputError("no pixel has a finite, non-zero spectrum")
    x = draw([(f, k) for f, k, _ in scr], sample, rng)
    ref, ref_rec = None, {}
    if reference is not None:
        rarr = _arrays(reference, "reference spectra")
        rscr = [screen_cube(a, min_norm=min_norm, noise_angle_deg=na) for a in rarr]
        ref = draw([(f, k) for f, k, _ in rscr], sample, np.random.default_rng(seed + 1))
        ref_rec = merge_records([r for _, _, r in rscr], "reference_")
    out = figures(x, ref, angle_deg)
    out.update(noise_angle_deg=na, **rec, **ref_rec)
    return out


def _range(values) -> str:
    v = [m for m in values if m is not None]
    if not v:
        return "n/a"
    return f"{min(v):.2f}°" if min(v) == max(v) else f"{min(v):.2f}–{max(v):.2f}°"


def format_diversity(d: dict, *, title: str = "spectral diversity") -> str:
    """Plain-text table of :func:`spectral_diversity` figures."""
    na = lambda v, f="{}": "n/a (no pixel left)" if v is None else f.format(v)  # noqa: E731
    total = d.get("pixels_total")
    rows = [("pixels sampled", f"{d['pixels']}" + (f" of {total}" if total is not None else "")
             + f" ({d['bands']} bands)")]
    if "excluded_noise" in d:
        rows.append((f"below the noise (angular noise > {d['noise_angle_deg']:g}°), excluded",
                     f"{d['excluded_noise']} ({d['excluded_noise_fraction']:.1%}); "
                     f"median noise {_range(d['noise_angle_median'])}"))
        srcs = sorted(set(d["noise_source"]) - {"neighbours"})
        if srcs:
            rows.append(("noise", "; ".join(srcs)))
        if d.get("excluded_invalid"):
            rows.append(("non-finite, zero or masked, excluded", str(d["excluded_invalid"])))
    ds = d["distinct_spectra"]
    med = [m for m in d.get("noise_angle_median") or [] if m is not None]
    if ds is None and med:
        # a bare "n/a" leaves the user guessing: the clustering angle must exceed the noise
        rows.append(("hint", f"every pixel is noisier than {d['noise_angle_deg']:g}°: cluster "
                             f"at an angle of at least {2 * max(med):.2g}° (--angle), or "
                             f"set the noise threshold (--noise-angle) or --min-norm"))
    rows += [(f"distinct spectra (leader clusters at {d['angle_deg']:g}°)",
              na(ds, "{}") + ("+" if ds is not None and ds >= LEADER_MAX else "")),
             ("components for 90 % of the variance", na(d["pcs_90"])),
             ("components for 99 % of the variance", na(d["pcs_99"]))]
    if "n_materials" in d:
        rows.insert(1, ("distinct materials (generator record)", str(d["n_materials"])))
    if "nn_angle_median" in d:
        if "reference_excluded_noise" in d:
            rows.append(("training pixels below the noise, excluded",
                         f"{d['reference_excluded_noise']} "
                         f"({d['reference_excluded_noise_fraction']:.1%})"))
        rows.append(("nearest training pixel, median angle", na(d["nn_angle_median"], "{:.2f}°")))
        rows.append(("nearest training pixel, 90th percentile", na(d["nn_angle_p90"], "{:.2f}°")))
    w = max(len(k) for k, _ in rows)
    return "\n".join([title, "-" * len(title)] + [f"{k:{w}s}  {v}" for k, v in rows])
