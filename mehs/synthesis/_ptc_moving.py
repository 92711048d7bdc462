"""The pixels a moving object changed between two exposures of the photon-transfer probe
(:func:`mehs.synthesis._ptc_groups.group_statistics` leaves them out whole).

Noise is independent across a pixel's bands and between neighbouring pixels; a moving
object shifts ``d = y_k − r·y_j`` of all the bands of the pixels it covers at once. A
pixel's score sums its samples' z-scores (each in units of the noise at its own level);
runs of consecutive pixels of the probe's whole lines are scored alike, which sees an
object whose every sample stays within a few σ even where a pixel has 2–3 bands.
"""

from __future__ import annotations

import numpy as np


#: A pixel whose z-scores (each sample's ``d`` about its group's median in MAD σ, clipped
#: at the 5σ clip) sum, over √(their number), to more than this many robust σ of that
#: score over the pixels (σ at least 1, the score's for independent noise) is dropped
#: from the statistics (:func:`_moving_pixels`): noise is independent across a pixel's
#: bands, a moving object shifts ``d`` of all its bands at once. The 5σ clip alone kept
#: its samples within 5σ: the simulator's moving patch doubled the measured gain. (At 4σ
#: its gain came out closer still, but pixels of static scenes went too: those whose
#: bands near saturation kept their lower noise only, a recovered curve's errors.)
MOVING_Z = 5.0


def _pixel_sums(z: np.ndarray, pix: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """float64 (n,) ``Σz`` and the count ``m`` of each pixel's samples ``z`` (``pix``: their
    pixels)."""
    return (np.bincount(pix, weights=z, minlength=n),
            np.bincount(pix, minlength=n).astype(np.float64))


def _outlying(score: np.ndarray) -> np.ndarray:
    """bool: the pixels whose score lies more than :data:`MOVING_Z` robust σ (median,
    scaled MAD, at least 1) from the median score."""
    out = np.zeros(score.shape, bool)
    ok = np.isfinite(score)
    if ok.sum() < 2:
        return out
    s = score[ok]
    centre = np.median(s)
    # at least the independent-noise score's σ: a MAD of 0 (a flat, dark scene whose
    # samples sit on their medians) would otherwise drop every pixel off the median
    scale = max(1.4826 * float(np.median(np.abs(s - centre))), 1.0)
    out[ok] = np.abs(s - centre) > MOVING_Z * scale
    return out


#: Half the run of consecutive probed pixels (whole lines, one after another) whose
#: scores :func:`_moving_pixels` also pools: a moving object covers neighbouring pixels
#: alike, noise is independent between them. Nine pixels × three bands see a shift of
#: 2σ a sample at 10σ, where a pixel's own three samples saw 3.5σ: the simulator's
#: moving patch had pushed the gain +30–76 % (3 bands) and +9–24 % (8 bands) high.
RUN_HALF = 4


def _moving_runs(s: np.ndarray, m: np.ndarray) -> np.ndarray:
    """bool (n,): pixels :func:`_outlying` by their own score ``Σz/√m`` (``s``: ``Σz``,
    ``m``: counts, float64 (n,) in probe order) or lying in a run of ``2·RUN_HALF + 1``
    consecutive pixels outlying by its score ``Σ_run z / √Σ_run m`` (so pixels up to
    ``2·RUN_HALF`` beyond an object's last far-out one go with it).

    A run ends where the probe does and may span the end of one probed line and the
    start of the next: pixels far apart, whose noise is as independent as neighbours'.
    """
    cs = np.concatenate(([0.0], np.cumsum(s)))
    cm = np.concatenate(([0.0], np.cumsum(m)))
    at = np.arange(s.size)
    lo, hi = np.maximum(at - RUN_HALF, 0), np.minimum(at + RUN_HALF + 1, s.size)
    S, M = cs[hi] - cs[lo], cm[hi] - cm[lo]
    run = _outlying(np.where(M > 0, S / np.sqrt(np.maximum(M, 1.0)), np.nan))
    # every pixel of an outlying run, not only its centre: the runs around an object's
    # far-out pixels reach 2·RUN_HALF beyond them, over its fringe of pixels shifted
    # too little to be seen even in runs (centres only: the 3-band gain +6–20 % high;
    # runs without the pixels their own scores flag: +4–6 %); the static pixels taken
    # along are chosen by their neighbours, not by their own noise
    cf = np.concatenate(([0], np.cumsum(run)))
    return _outlying(np.where(m > 0, s / np.sqrt(np.maximum(m, 1.0)), np.nan)) | (
        cf[hi] - cf[lo] > 0)


#: Bands (evenly spread) of every pixel that score it when the even subset flags one;
#: a probe of at most this many bands is scored on all of them.
SCORE_BANDS = 64


def _moving_pixels(y_j, y_k, r, rj, rk, sat, nbr, table, lo, med, scale, usable,
                   subset, pix_s, e_s, g_s, sd_s) -> np.ndarray | None:
    """bool (n,): the pixels whose exposures disagree across their bands as no noise
    does (a moving object), or None when none does.

    A pixel's score is ``Σz/√m`` of its ``m`` samples' z-scores about their groups'
    medians, in units of the noise σ at the sample's own level ``q`` (``scale`` =
    ``(madz, a, c)``: σ = ``madz[g]·√(a·max(q, 0) + c)``, see
    :func:`mehs.synthesis._ptc_groups._group_clip`; a group mixing levels, whose one MAD
    σ would overstate the z-scores of its bright samples, then scores static pixels as
    noise does; ``usable``: groups with a σ); a run of neighbouring pixels is scored
    alike (:func:`_moving_runs`). Noise leaves both about N(0, 1), each sample's own
    noise weighing 1/√m in it, so dropping a pixel at :data:`MOVING_Z` σ selects no
    sample by its noise; a moving object shifts ``y_k − r·y_j`` of every band of the
    pixels it covers, and scores far out even where each sample stays inside the clip.
    The even subset scores each pixel first (free: its z-scores are at hand); only when
    that flags one are the pixels scored again on every band, or :data:`SCORE_BANDS`
    of more (the subset holds three samples a pixel of a 16384-pixel probe, or one of a
    3-band probe: too few to see a patch moving a few σ; every band of every pixel of
    204 would double the statistics' time). The subset: each sample's ``d`` about its
    group's median (``e_s``), group (``g_s``), noise σ at its own level (``sd_s``) and
    pixel (``pix_s``); ``subset`` False where it is every sample.
    """
    from mehs.synthesis._ptc_groups import _own_level

    n, nb = y_j.shape
    madz, a, c = scale
    inv = np.where(usable, 1.0 / np.where(usable, madz, 1.0), 0.0)    # 0: no z-score

    def zscores(d, g, q):
        g = g.astype(np.intp)
        z = (d - np.take(med, g)) * np.take(inv, g) / np.sqrt(a * np.maximum(q, 0.0) + c)
        return np.clip(z, -5.0, 5.0)

    # (d − med)·inv/σ, as zscores forms it, from the parts at hand
    z_s = np.clip(e_s * np.take(inv, g_s) / sd_s, -5.0, 5.0)
    moving = _moving_runs(*_pixel_sums(z_s, pix_s, n))
    if not moving.any():
        return None
    if subset:                              # a subset: score the pixels on more bands
        from mehs.synthesis._ptc_groups import CELL_BITS
        from mehs.synthesis._ptc_numpy import cell_keys, cells_flags

        if nb <= SCORE_BANDS:
            # every band: the even ones alone (below) left a 3-band probe one sample a
            # pixel to score, and the patch's fringe pushed the gain +30–40 % high
            cells, bad = cells_flags(y_j, y_k, rj, rk, sat, nbr, CELL_BITS)
            ya, yb = y_j.astype(np.float64), y_k.astype(np.float64)
        else:
            # even bands b = 0, s, 2s, … (s even), whose instruments are the bands b + 1:
            # strided views, no gathers
            s = 2 * max(1, -(-nb // (2 * SCORE_BANDS)))
            at, nx = np.s_[:, 0:nb - 1:s], np.s_[:, 1:nb:s]
            cells = cell_keys(np.asarray(y_j[nx] + y_k[nx], dtype=np.float32), CELL_BITS)
            sat_k = rk[nx] >= sat[nx[1]]
            bad = (rk[at] >= sat[at[1]]) | sat_k | (rj[at] >= sat[at[1]])
            ya, yb = y_j[at].astype(np.float64), y_k[at].astype(np.float64)
        z = zscores(yb - r * ya, np.take(table, np.clip(cells - lo, 0, table.size - 1)),
                    _own_level(ya, yb, r))
        z[bad] = 0.0
        m = bad.shape[1] - np.count_nonzero(bad, axis=1)
        moving = _moving_runs(z.sum(axis=1), m.astype(np.float64))
    return moving if moving.any() else None
