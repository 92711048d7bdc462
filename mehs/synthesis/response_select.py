"""Which dark-offset solve a shared response curve keeps: the one that fits pixels it was
not solved from (``offset="auto"`` of :func:`mehs.synthesis.fuse_response.recover_response`).

Both solves of the model ``f(Z_ij) − f(D_ij) = E_i·Δt_j`` are right on the data and differ
in the prior that fills what the data leave open — most of the curve on a dark bracket,
whose samples crowd the dark level:

- the rounds (Debevec–Malik in the log domain) prefer a straight ``g = ln f``: a power law,
  which a gamma sensor's inverse response is; a linear sensor's ``ln(z)`` bends sharply
  near the dark level, and the rounds never pin the free constant of ``f`` (``f → f + k``
  cancels in ``f(Z) − f(D)``): their log-domain prior drives it up round after round
  (sodium-lamp scene at 10⁻³ of its light, linear sensor: ``f(z_d)/f(300)`` 0.10 after one
  round, 0.73 after 60, 0.88 after 300; the truth 0.11), and the curve follows;
- the direct solve (:mod:`mehs.synthesis.response_offset`) prefers a straight ``f``: a
  linear sensor's, not a gamma sensor's.

Neither is right on every sensor, so on a dark bracket (:func:`is_dark`) the data decide:
each curve is scored by the offset model's residual on *held-out* samples — pixels that
neither solve saw, drawn by the same stratified sampler — with ``E`` fitted per pixel, in
the noise's units (``σ² ∝ y + y₀``, as the direct solve's weights), each curve on its own
scale set by the samples' median secant slope (the scale is free). Measured against the
simulator's truth (shared curves, 90 dark brackets of 48² pixels, 9 bands: 5 scene kinds ×
light ×10⁻², ×10⁻³ × linear, gamma and s-curve sensors × 2, 3 and 5 exposures ×4; the
merged radiance of the pixels with ≥ 20 DN of true signal per brightness decile, against
the true curve's merge, worst decile): the rounds (the former default) 0.3–34 %, mean
8.7 %; the direct solve 0–55 %, mean 8.8 %; the one kept here 0–15 %, mean 3.7 % (the true
curve's own merge: mean 2.3 % from the truth) — the better of the two on 81 of the 90, and
worse than the rounds by more than 0.05 points on one (1.1 points). The 45 brackets at
full light (longest exposure's p90 360–2960 DN) keep the rounds: 0.5–6.1 %, mean 1.8 %.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mehs.errors import InputError


def auto_offset_solve(direct: Callable[[], tuple], rounds: Callable[[], tuple],
                      cand: np.ndarray, cdark: np.ndarray, used: np.ndarray, n: int,
                      seed: int, times: np.ndarray, bit_depth: int, level_w: np.ndarray,
                      bright: str = "rounds", stiffer: Callable[[float], tuple] | None = None,
                      candidates: list[float] = ()):
    """``offset="auto"`` for a shared curve: on a dark bracket (:func:`is_dark`) both solves,
    keeping the one :func:`pick_solve` prefers on held-out pixels; else ``bright``'s solve
    (the rounds; the direct one for the reference of per-band curves, as before), but with
    the rounds also the direct solve where the dark level lies near 0
    (:data:`LOW_BLACK_FRACTION`), keeping the one :func:`pick_bright` prefers.

    ``direct``, ``rounds``: the two solves, each returning ``(curve, Z, D, f)``;
    ``cand``, ``cdark`` ``(P, M, C)`` the candidate levels and raw darks, ``used``
    ``(C, n_used)`` the candidates the solves sampled, ``n`` held-out pixels per channel.
    ``stiffer(λ)``: the rounds continued at a larger λ (``candidates``), for a bright bracket
    that keeps the rounds (:func:`pick_smoothness`); None: the λ given stays.
    Returns the kept solve's tuple, its curve's parameters extended by the figures.
    """
    dark, p90 = is_dark(cand, cdark, times, bit_depth)
    black = float(np.median(cdark))
    info = {"offset_choice": "auto", "offset_signal_p90": p90, "offset_dark_level": black}
    if not dark and bright != "rounds":
        out = direct()
        out[0].parameters.update(info)
        return out
    # a bright bracket: the direct solve too only where the rounds' prior may fail (its cost
    # doubled a 512² recovery, 0.45 → 1.0 s)
    both = dark or black < LOW_BLACK_FRACTION * (1 << bit_depth)
    if not both and (stiffer is None or not candidates):
        out = rounds()
        out[0].parameters.update(info)
        return out
    got, errors = {}, []
    for name, run in (("direct", direct), ("rounds", rounds)) if both else (("rounds", rounds),):
        try:
            got[name] = run()
        except InputError as exc:    # e.g. a singular direct system: the other may hold
            errors.append(exc)
    if not got:
        raise errors[0]
    Zh, Dh = held_out_samples(cand, cdark, used, n, seed + 1, bit_depth)
    misfits = {k: offset_misfit(r[0].table()[0], Zh, Dh, times, level_w) for k, r in got.items()}
    choice, stats = pick_solve(misfits) if dark else pick_bright(misfits)
    out = got[choice]
    if choice == "rounds" and not dark and stiffer is not None and candidates:
        base = out[0].smoothness
        runs = {base: out}
        scores = {base: misfits["rounds"]}
        for lam in candidates:
            runs[lam] = stiffer(lam)
            scores[lam] = offset_misfit(runs[lam][0].table()[0], Zh, Dh, times, level_w)
        lam, choice_stats = pick_smoothness(scores, base)
        out = runs[lam]
        out[0].parameters["smoothness_choice"] = choice_stats
    out[0].parameters.update({**info, "offset_misfit": stats})
    return out


def held_out_samples(cand: np.ndarray, cdark: np.ndarray, used: np.ndarray, n: int,
                     seed: int, bit_depth: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples of pixels the solve did not see, per channel.

    Parameters
    ----------
    cand, cdark
        int32 / float32 ``(P, M, C)``: candidate levels and their raw darks.
    used
        int64 ``(C, n_used)``: the candidate indices the solve sampled (−1: unfilled).
    n
        Held-out pixels per channel (fewer where the candidates run out).

    Returns
    -------
    ``Z`` int32 ``(n, P, C)`` (``L − 1``, weight 0, in unfilled slots) and ``D`` float
    ``(n, P, C)`` their raw darks.
    """
    from mehs.synthesis.fuse_response import sample_shared

    L = 1 << bit_depth
    rest = np.array(cand, dtype=np.int32, copy=True)
    P, M, C = rest.shape
    ch = np.broadcast_to(np.arange(C)[:, None], used.shape)
    ok = used >= 0
    # a used pixel is made ineligible in its channel (saturated in every exposure)
    rest[:, used[ok], ch[ok]] = L - 1
    Z, idx = sample_shared(rest, n, seed, bit_depth)
    D = np.take_along_axis(cdark.transpose(2, 1, 0), np.maximum(idx, 0)[:, :, None],
                           axis=1).transpose(1, 2, 0)
    return Z, D


def offset_misfit(g: np.ndarray, Z: np.ndarray, D: np.ndarray, times: np.ndarray,
                  level_w: np.ndarray) -> np.ndarray:
    """Squared residuals of ``f(Z) − f(D) = E·Δt`` (``f = exp g``) in noise units, summed
    per (pixel, channel): float64 ``(n·C,)``, NaN where the pixel has no usable pair.

    ``g`` ``(L,)`` a shared raw-level curve; ``Z``, ``D`` ``(n, P, C)`` levels and raw
    darks; ``E`` fitted per (pixel, channel) by weighted least squares. The noise is
    ``σ² = y + y₀`` with ``y`` the signal in levels (``f`` divided by its median secant
    slope ``(f(Z) − f(D))/(Z − D)`` over the samples, which fixes the free scale) and
    ``y₀ = L/256`` levels (the direct solve's floor). Samples at or below their dark
    level, saturated ones, and pixels with fewer than two of the rest are left out — the
    same for every curve, so that two curves' residuals pair up pixel by pixel.
    """
    L = level_w.size
    f = np.exp(np.asarray(g, dtype=np.float64) - np.max(g))
    y = f[Z] - np.interp(D, np.arange(L), f)
    use = (level_w[Z] > 0) & (Z > np.ceil(D))
    use &= use.sum(axis=1, keepdims=True) >= 2
    out = np.full(Z.shape[0] * Z.shape[2], np.nan)
    if not use.any():
        return out
    s = np.median(y[use] / (Z[use] - D[use]))
    if not (np.isfinite(s) and s > 0):
        return out
    y = y / s
    w = np.where(use, 1.0 / (np.maximum(y, 0.0) + L / 256.0), 0.0)
    t = np.asarray(times, dtype=np.float64)[None, :, None]
    E = (w * y * t).sum(axis=1) / np.maximum((w * t * t).sum(axis=1), 1e-300)
    r2 = (w * (y - E[:, None, :] * t) ** 2).sum(axis=1)
    return np.where(use.any(axis=1), r2, np.nan).ravel()


#: A bracket is dark when the 90th percentile of its longest exposure's signal (raw − dark,
#: saturated samples counted as full scale) lies below this fraction of the levels: the
#: data then crowd the dark level and the prior fills most of the curve, and the two solves
#: differ by 15–55 % (light ×10⁻²…10⁻³ of the simulator's scenes: 4–29 DN; at ×1: 360–2960
#: DN). On brighter brackets the data pin the curve, both solves are within their sampling
#: ripple of each other, and the held-out misfit — the direct solve's own objective — leans
#: to it without its radiance being better (s-curve sensor, 3 exposures ×8, 204 bands: paired
#: z −19, radiance 3.0 % off the truth against the rounds' 2.3 %): the rounds stay there.
DARK_SIGNAL_FRACTION = 1.0 / 16.0


def is_dark(cand: np.ndarray, cdark: np.ndarray, times: np.ndarray, bit_depth: int
            ) -> tuple[bool, float]:
    """Whether a bracket is dark (:data:`DARK_SIGNAL_FRACTION`), from its candidate levels
    and raw darks ``(P, M, C)``; returns the verdict and the percentile (levels)."""
    j = int(np.argmax(times))
    p90 = float(np.percentile(cand[j].astype(np.float64) - cdark[j], 90))
    return p90 < DARK_SIGNAL_FRACTION * (1 << bit_depth), p90


#: On a bright bracket the rounds are kept unless the direct solve's mean held-out misfit is
#: below this fraction of theirs. An expansive sensor (gamma > 1) puts the black level a few
#: raw levels above 0 (gamma 1.4: ~5 of 4096), where ``ln f`` bends as ``−1/(γz²)``: the
#: rounds' log-domain smoothness straightens it (at 60 rounds and at 300 alike, stiffer λ
#: worse) and their radiance ran 5–25 % off the true curve's merge across brightness deciles
#: (natural scene, 6 × ×4: decile ptp 26 %, median 8 %; the direct solve 1.0 % / 0.35 %).
#: The misfit tells them apart by far: direct/rounds 0.12–0.15 there, 0.90–1.03 on gamma-0.8,
#: linear and s-curve brackets (48² px, 51 bands; colorchecker, lamp, natural), where the
#: rounds stay (their s-curve radiance is the better one at ×8: 1.6 vs 5.4 % ptp).
BRIGHT_DIRECT_RATIO = 0.5
#: A bright bracket is solved both ways (and :func:`pick_bright` asked) only when its median
#: raw dark level lies below this fraction of the levels (16 of 4096): where ``ln f`` bends
#: most. The simulator's dark level: gamma 2 / 1.4 / 1.2 / 1.1 ~0 / 5 / 13 / 20; s-curve 22;
#: linear 32; gamma 0.8 84 (black level 32 DN before the response).
LOW_BLACK_FRACTION = 1.0 / 256.0


def mean_misfits(misfits: dict) -> dict:
    """Each candidate's mean held-out misfit (None where no held-out pixel is usable): the
    figure :func:`pick_solve`, :func:`pick_bright` and :func:`pick_smoothness` compare."""
    return {k: (float(np.nanmean(r)) if np.isfinite(r).any() else None)
            for k, r in misfits.items()}


def pick_bright(misfits: dict[str, np.ndarray]) -> tuple[str, dict]:
    """The solve a bright bracket keeps (:data:`BRIGHT_DIRECT_RATIO`): ``"rounds"`` unless
    the direct solve's mean held-out misfit is below that fraction of theirs; the one
    solved when only one was. Returns the choice and each mean misfit (None: not
    measurable), as :func:`pick_solve`."""
    stats: dict = mean_misfits(misfits)
    if set(misfits) != {"direct", "rounds"}:
        return next(iter(misfits)), stats
    d, r = stats["direct"], stats["rounds"]
    keep = "direct" if d is not None and r is not None and d < BRIGHT_DIRECT_RATIO * r else "rounds"
    return keep, stats


def pick_smoothness(misfits: dict[float, np.ndarray], base: float) -> tuple[float, dict]:
    """The largest λ whose mean held-out misfit is at most (1 +
    :data:`~mehs.synthesis.response.SMOOTHNESS_TOLERANCE`) times the ``base`` λ's (the
    default's, whose curve the others continue from); ``base`` when its misfit is not
    measurable. Returns λ and figures for the curve's parameters: each candidate's mean
    misfit relative to the base's (JSON keys: λ as text)."""
    from mehs.synthesis.response import SMOOTHNESS_TOLERANCE

    means = {lam: m for lam, m in mean_misfits(misfits).items() if m is not None}
    ref = means.get(base)
    rel = {lam: (m / ref - 1.0 if ref else None) for lam, m in means.items()}
    keep = base
    if ref:
        keep = max([lam for lam, v in rel.items() if v is not None
                    and v <= SMOOTHNESS_TOLERANCE] + [base])
    return keep, {"chosen": float(keep), "tolerance": SMOOTHNESS_TOLERANCE,
                  "misfit_rise": {f"{lam:g}": rel.get(lam) for lam in misfits}}


def pick_solve(misfits: dict[str, np.ndarray]) -> tuple[str, dict]:
    """``"direct"`` when its held-out misfit is below the rounds' (mean of the per-pixel
    differences), else ``"rounds"`` (also when no held-out pixel is usable); the one solved
    when only one was. Returns the choice and figures for the curve's parameters: each mean
    misfit (None if not measurable) and the paired difference's z-score."""
    stats: dict = mean_misfits(misfits)
    if set(misfits) != {"direct", "rounds"}:
        return next(iter(misfits)), stats
    d = misfits["direct"] - misfits["rounds"]
    d = d[np.isfinite(d)]
    if d.size < 2:
        return "rounds", stats
    se = d.std(ddof=1) / np.sqrt(d.size)
    z = float(d.mean() / se) if se > 0 else 0.0
    stats["z_direct_vs_rounds"] = z
    return ("direct" if d.mean() < 0 else "rounds"), stats
