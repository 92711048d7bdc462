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

References
----------
- Hartigan (1975), *Clustering Algorithms*, Wiley (the leader algorithm).
- Chakrabarti & Zickler (2011), "Statistics of real-world hyperspectral images", CVPR.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from mehs.errors import InputError


def unit_spectra(cubes: np.ndarray | Iterable[np.ndarray], *, sample: int | None = None,
                 seed: int = 0) -> np.ndarray:
    """Pixels of one or more ``(..., B)`` arrays as unit-norm float64 rows ``(N, B)``.

    Zero-norm and non-finite pixels are dropped; ``sample`` draws that many rows at random.
    """
    arrays = [cubes] if isinstance(cubes, np.ndarray) else list(cubes)
    if not arrays:
        raise InputError("no spectra given")
    bands = {np.shape(a)[-1] for a in arrays}
    if len(bands) != 1:
        raise InputError(f"the cubes have different band counts {sorted(bands)}")
    b = bands.pop()
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


def spectral_diversity(cubes, reference=None, *, sample: int = 20000, angle_deg: float = 1.0,
                       seed: int = 0) -> dict:
    """Diversity figures of ``cubes`` (one ``(H, W, B)`` array or several), see module notes.

    ``reference``: training cubes for the nearest-training-pixel angle (optional).
    """
    x = unit_spectra(cubes, sample=sample, seed=seed)
    p90, p99 = pcs_for(x)
    out = {"pixels": int(x.shape[0]), "bands": int(x.shape[1]), "angle_deg": float(angle_deg),
           "distinct_spectra": leader_clusters(x[:min(x.shape[0], 8192)], angle_deg),
           "pcs_90": p90, "pcs_99": p99}
    if reference is not None:
        ref = unit_spectra(reference, sample=sample, seed=seed + 1)
        if ref.shape[1] != x.shape[1]:
            raise InputError(f"reference has {ref.shape[1]} bands, the cubes {x.shape[1]}")
        a = nearest_angles(x[:min(x.shape[0], 4000)], ref)
        out["nn_angle_median"] = float(np.median(a))
        out["nn_angle_p90"] = float(np.percentile(a, 90))
    return out


def format_diversity(d: dict, *, title: str = "spectral diversity") -> str:
    """Plain-text table of :func:`spectral_diversity` figures."""
    rows = [("pixels sampled", f"{d['pixels']} ({d['bands']} bands)"),
            (f"distinct spectra (leader clusters at {d['angle_deg']:g}°)",
             f"{d['distinct_spectra']}{'+' if d['distinct_spectra'] >= 8192 else ''}"),
            ("components for 90 % of the variance", str(d["pcs_90"])),
            ("components for 99 % of the variance", str(d["pcs_99"]))]
    if "n_materials" in d:
        rows.insert(1, ("distinct materials (generator record)", str(d["n_materials"])))
    if "nn_angle_median" in d:
        rows.append(("nearest training pixel, median angle", f"{d['nn_angle_median']:.2f}°"))
        rows.append(("nearest training pixel, 90th percentile", f"{d['nn_angle_p90']:.2f}°"))
    w = max(len(k) for k, _ in rows)
    return "\n".join([title, "-" * len(title)] + [f"{k:{w}s}  {v}" for k, v in rows])
