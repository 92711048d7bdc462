"""Direct solve of the response model with a dark offset: ``f(Z_ij) − f(D_ij) = E_i·Δt_j``.

Raw levels include the dark level ``D`` (black level, column pattern, dark current),
which is added *before* the sensor's non-linearity. Debevec and Malik's model
``ln f(Z_ij) = ln E_i + ln Δt_j`` has no room for it; in the linear domain of the
inverse response ``f`` it is exact and linear in the unknowns — the table ``f``
(``L`` values) and one ``E_i`` per sampled pixel — since ``f(D)`` at a fractional dark
level is the linear interpolation of two table entries (the merge's own
:func:`mehs.synthesis.fuse._exp_curve_at`). So one weighted, smoothed linear
least-squares solve reaches what the fixed-point rounds of
:func:`mehs.synthesis.fuse_response.recover_response` approach sublinearly.

Measured against the simulator's truth (radiance bias across brightness deciles, one
global scale removed; the benchmark's scenes): per-band
curves −15…+2 % (gamma, 5 exposures ×4) and −38…+8 % (linear, 3 × ×8) after 12
rounds, −1…+5 % and −5…+1 % here. A shared curve: 60 over-relaxed rounds and this
solve are within the noise of each other on 3 exposures and this one is better on 5
(ptp 1.2 % vs 4.9 %), worse on 2 (12.7 % vs 5.7 %: the prior fills more there); it
costs ~2× the rounds (SuperLU on an L×L system, vs the rounds' numba CG). On dark brackets
the prior decides (straight ``f`` here, straight ``ln f`` in the rounds), so ``offset="auto"``
solves a shared curve both ways and keeps the one that fits held-out pixels better
(:mod:`mehs.synthesis.response_select`).

Per-band curves take the shared curve of the bracket as pilot and, with ``shape_prior``,
as the shape their smoothness prefers; :func:`tie_bands_to_reference` then puts every
band on its scale. A dark band (the blue end under a sodium lamp) had neither data at the
gauge level nor enough to set its own shape near black: its radiance ran −100 % (s-curve:
its table fell to −1e23 above its data), +71 % (gamma) of the truth, or the solve was
singular (natural scene); now within 4 % of the true curve's (9 bands, 3 exposures ×4).

Two constants are free: ``f → s·f`` with ``E → s·E`` (the scale) and ``f → f + k``
(cancels in ``f(Z) − f(D)``). They are fixed by ``f(z_d) = 0`` at the median dark level
and ``f(z_1) = 1`` at a level well above it; the caller then applies the curves'
normalisation (``g = ln f``, ``g(Z_mid) = ln Z_mid``, the constant ``k`` chosen by
:func:`match_constant`).

Weights (noise-aware): a sample's residual is in linear DN, whose noise is shot noise
plus a floor, ``σ² ∝ y + y₀`` (``y = f(Z) − f(D)``, the pilot's linear signal — the
plain Debevec–Malik curve — ``y₀`` the signal ``L/256`` raw levels above the dark,
~16 DN at 12 bits: the simulated sensor's read noise, 2 DN, and gain 0.25 DN/e⁻, give
``σ_read²/gain = 16``). That is the inverse-variance weighting of the Poisson merge
(Hanji et al. 2020). The level weighting (Debevec's hat by default) multiplies it: it
tapers the levels next to saturation, where a noisy pixel is partly clipped and its
unclipped samples are biased low.

Smoothness: ``λ'·Σ_z [w(z)·f''(z)/f'(z)]²`` with the pilot's slope ``f'``: the curvature
relative to the slope, which is what ``g''`` measures in the log domain away from black
and which does not depend on the free scale; a linear sensor's ``f`` costs nothing.
``λ' = λ·ρ·((L−1)/255)²·SMOOTHNESS_SCALE`` with ``ρ = N·P/L`` samples per level.
"""

from __future__ import annotations

import numpy as np

from mehs.errors import InputError
from mehs.threadwarn import local_filter

#: Makes λ = 100 (the default) a prior of the right strength in the linear domain,
#: scanned over 1e3…1e5 on simulated 12-bit brackets (gamma, linear, s-curve sensors,
#: 2–5 exposures): at 1e5 the per-band radiance bias across brightness deciles fell from
#: 17–45 % (12 offset rounds) to ~6 %; at 1e3 the curve follows the noise (±20 %). At
#: λ = 300 (3× :data:`mehs.synthesis.response.DEFAULT_SMOOTHNESS`) per-band curves
#: (9 bands, colorchecker, gamma, 5 exposures ×4) came 0.44 % from the true curve's merge
#: (decile ptp 1.0 %) against λ = 100's 0.51 % (2.0 %); λ = 1000: 1.8 % (7.8 %).
SMOOTHNESS_SCALE = 1e5
#: λ' of the shape prior (``shape_prior``) relative to the straight-line one: per-band
#: curves (9 bands, 3–5 exposures, colorchecker/lamp/natural scenes, gamma and s-curve
#: sensors) had their darkest-decile radiance bias at ×0.1 of −13…−28 %, at ×1 −7…−20 %,
#: at ×10 −2…−17 % (the true curve: −2…−14 %), at ×100 the shared curve's
SHAPE_PRIOR_SCALE = 10.0
#: SuperLU's column ordering: the system is symmetric, and the minimum-degree ordering of
#: A + Aᵀ factorises it ~20 % faster than the default COLAMD
PERMC = "MMD_AT_PLUS_A"


def _pilot_linear(pilot: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """``f = exp(g)`` of a pilot curve table (C, L), and its slope per level (> 0).

    ``lo…hi``: the levels the samples cover. Outside them the pilot is the plain
    solve's extrapolation (``g`` straight, ``f`` exponential), which says nothing about the
    sensor: ``f`` is continued there as a straight line (the prior's own shape), and is
    scaled to its largest value *inside* them. On a dark bracket (data up to level ~240
    of 4096) the extrapolation rose ~e⁵⁰ to level L−1: scaled to it, the data's slopes
    underflowed to 1e-22 and the smoothness vanished at the top levels, whose solved
    ``f`` then ran to −1e27 (a flat curve after :func:`match_constant`, or a singular
    per-band system)."""
    g = np.asarray(pilot, dtype=np.float64)
    L = g.shape[1]
    f = np.exp(np.clip(g - g[:, lo:hi + 1].max(axis=1, keepdims=True), -700.0, 0.0))
    lev = np.arange(L)
    k = max(1, min(16, (hi - lo) // 4))
    mean = (f[:, hi] - f[:, lo]) / max(hi - lo, 1)
    s_hi = np.maximum((f[:, hi] - f[:, hi - k]) / k if hi - k >= lo else mean, mean)
    s_lo = np.maximum((f[:, lo + k] - f[:, lo]) / k if lo + k <= hi else mean, 0.0)
    f = np.where(lev > hi, f[:, hi:hi + 1] + s_hi[:, None] * (lev - hi), f)
    f = np.where(lev < lo, f[:, lo:lo + 1] - s_lo[:, None] * (lo - lev), f)
    slope = np.gradient(f, axis=1)
    # a pilot flat or falling somewhere (noise at unseen levels) must not give the
    # smoothness an infinite weight there: floor at 1e-3 of the median slope
    floor = 1e-3 * np.median(np.abs(slope), axis=1, keepdims=True)
    return f, np.maximum(slope, np.maximum(floor, 1e-300))


def solve_offset_response(Z: np.ndarray, D: np.ndarray, times: np.ndarray, level_w: np.ndarray,
                          pilot: np.ndarray, *, smoothness: float,
                          shared: bool, shape_prior: bool = False) -> tuple[np.ndarray, dict]:
    """The table ``f`` (linear DN, gauge ``f(z_d) = 0``, ``f(z_1) = 1``) per channel.

    Parameters
    ----------
    Z
        int ``(N, P, C)`` raw levels; ``L − 1`` marks a saturated sample.
    D
        float ``(N, P, C)`` the raw dark level of each sample.
    times
        ``(P,)`` exposure times.
    level_w
        ``(L,)`` the level weighting (0 at 0 and L−1): saturated samples get none.
    pilot
        ``(C', L)`` log curve (the plain Debevec–Malik solve): the weights and the
        smoothness's slope; C' = 1 for a shared curve, else C.
    shared
        One curve for all C channels (every (pixel, channel) has its own ``E``).
    shape_prior
        The smoothness measures the curvature of ``f`` as a function of the pilot's
        linear signal (second differences on the pilot's grid) instead of the levels':
        the pilot's shape, not a straight line, then costs nothing. For per-band curves
        with a shared curve as pilot: a band whose samples are few (a dark band) falls
        back to the common non-linearity instead of to a linear sensor.

    Returns
    -------
    ``f`` float64 ``(C', L)`` and solver figures (``monotonic_violations``: levels within
    the observed range where the solved ``f`` does not rise, before they are levelled).
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    N, P, C = Z.shape
    L = level_w.size
    t = np.asarray(times, dtype=np.float64)
    if shared:
        Zc = Z.transpose(1, 0, 2).reshape(P, N * C).T[None]       # (1, N·C, P)
        Dc = D.transpose(1, 0, 2).reshape(P, N * C).T[None]
    else:
        Zc, Dc = Z.transpose(2, 0, 1), D.transpose(2, 0, 1)       # (C, N, P)
    seen = Z[level_w[Z] > 0]
    if seen.size == 0:
        raise InputError("no sample is unsaturated; the bracket cannot determine the response")
    lo, hi = int(seen.min()), int(seen.max())
    fp_all, slope_all = _pilot_linear(np.asarray(pilot, dtype=np.float64), lo, hi)
    out = np.empty((Zc.shape[0], L))
    violations = []
    for c in range(Zc.shape[0]):
        out[c], v = _solve_channel(Zc[c], np.clip(Dc[c], 0.0, L - 2.0), t, level_w,
                                   fp_all[min(c, fp_all.shape[0] - 1)],
                                   slope_all[min(c, slope_all.shape[0] - 1)],
                                   smoothness, sp, spla, shape_prior, (lo, hi))
        violations.append(v)
    return out, {"solver": "offset-direct", "monotonic_violations": int(np.sum(violations))}


def _second_differences(fp, shape_prior, sp):
    """(L−2, L) second differences, in units of ``f''`` per level: on the levels, or with
    ``shape_prior`` on the grid ``x = fp`` (the pilot's linear signal), scaled by ``x'²``
    so that both agree where the pilot is linear (``a·x + b`` has none)."""
    L = fp.size
    if not shape_prior:
        return sp.diags([np.ones(L - 2), -2 * np.ones(L - 2), np.ones(L - 2)], [0, 1, 2],
                        shape=(L - 2, L))
    dx = np.diff(fp)
    # the grid must rise strictly: a flat or falling pilot step (levelled noise, the floor
    # below its lowest level) gets 1e-3 of the median step
    dx = np.maximum(dx, max(1e-3 * np.median(np.abs(dx)), 1e-300))
    h1, h2 = dx[:-1], dx[1:]
    xs2 = (0.5 * (h1 + h2)) ** 2
    return sp.diags([2 * xs2 / (h1 * (h1 + h2)), -2 * xs2 / (h1 * h2), 2 * xs2 / (h2 * (h1 + h2))],
                    [0, 1, 2], shape=(L - 2, L))


def _solve_channel(Z, D, t, level_w, fp, slope, smoothness, sp, spla, shape_prior=False,
                   zrange=(0, 1 << 30)):
    """One curve: (N, P) levels ``Z`` and darks ``D`` → ``f`` (L,), count of non-rising levels."""
    N, P = Z.shape
    L = level_w.size
    d0 = np.floor(D).astype(np.intp)
    a = D - d0
    # the pilot's linear signal of each sample and the noise floor y0 (module docstring)
    zd = int(np.rint(np.median(D)))
    y = np.interp(Z, np.arange(L), fp) - np.interp(D, np.arange(L), fp)
    y0 = max(fp[min(zd + L // 256, L - 1)] - fp[zd], 1e-12 * fp.max())
    w = level_w[Z] / np.sqrt(np.maximum(y, 0.0) + y0)
    use = (level_w[Z] > 0) & (Z > np.ceil(D))       # at or below its dark: clipped, no signal
    w = np.where(use, w, 0.0)
    w[(use.sum(axis=1) < 2)] = 0.0                   # one exposure ties no levels
    if not np.any(w > 0):
        raise InputError("no pixel has two usable (unsaturated, above-dark) exposures; "
                         "the bracket cannot determine the response")
    w /= np.median(w[w > 0])                         # scale-free: λ keeps its meaning
    w2 = w * w
    # a_ij: +1 at Z, −(1 − a) at ⌊D⌋, −a at ⌊D⌋ + 1 — the row of f(Z) − f(D)
    idx = np.stack([Z, d0, d0 + 1], axis=2)                       # (N, P, 3)
    cf = np.stack([np.ones_like(a), a - 1.0, -a], axis=2)
    # E_i eliminated (Schur complement): Σ_j w²·a aᵀ − u uᵀ/T, u = Σ_j w²·t_j·a, T = Σ_j w²·t_j²
    T = (w2 * t * t).sum(axis=1)
    ok = T > 0
    rows = [np.broadcast_to(idx[:, :, :, None], (N, P, 3, 3)).ravel()]
    cols = [np.broadcast_to(idx[:, :, None, :], (N, P, 3, 3)).ravel()]
    vals = [(w2[:, :, None, None] * cf[:, :, :, None] * cf[:, :, None, :]).ravel()]
    ui = idx.reshape(N, 3 * P)[ok]
    uv = ((w2 * t)[:, :, None] * cf).reshape(N, 3 * P)[ok]
    rows.append(np.broadcast_to(ui[:, :, None], (ui.shape[0], 3 * P, 3 * P)).ravel())
    cols.append(np.broadcast_to(ui[:, None, :], (ui.shape[0], 3 * P, 3 * P)).ravel())
    vals.append((-uv[:, :, None] * uv[:, None, :] / T[ok][:, None, None]).ravel())
    A = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(L, L)).tocsr()
    # smoothness on f''/f' (module docstring), floor on the level weights as Debevec–Malik
    rho = N * P / L
    lam = smoothness * rho * ((L - 1) / 255.0) ** 2 * SMOOTHNESS_SCALE
    if shape_prior:
        lam *= SHAPE_PRIOR_SCALE
    zs = np.arange(1, L - 1)
    # normalised at L/2, or the nearest level the samples cover (a dark bracket's data end
    # far below it, where the pilot's slope is its continuation, not a measurement)
    zr = int(np.clip(L // 2, *zrange))
    ws = np.maximum(level_w[zs], 1e-3) / slope[zs] * slope[zr]
    D2 = _second_differences(fp, shape_prior, sp)
    A = A + lam * (D2.T @ sp.diags(ws ** 2) @ D2)
    # the gauge: f(z_d) = 0 at the median dark, f(z_1) = 1 a quarter of the range higher
    z1 = min(L - 2, max(L // 2, zd + L // 4))
    keep = np.ones(L, bool)
    keep[[zd, z1]] = False
    A = A.tocsc()
    Ak = A[keep][:, keep]
    b = -np.asarray(A[keep][:, [z1]].todense()).ravel()
    # (a singular system shows as non-finite values, checked below; this thread only:
    # scenes are built as threads, and catch_warnings is process-wide)
    with local_filter("ignore"):
        x = spla.spsolve(Ak.tocsc(), b, permc_spec=PERMC)
    f = np.zeros(L)
    f[keep] = x
    f[z1] = 1.0
    if not np.all(np.isfinite(f)):
        raise InputError("the response system with the dark offset is singular: the samples "
                         "do not tie the levels together (too few overlapping exposures?)")
    # monotonic over the levels the samples cover; a dip (noise at sparse levels) is
    # levelled so the merge never maps a higher level to less signal, and counted
    seen = Z[w > 0]
    lo, hi = int(min(seen.min(), zd)), int(seen.max())
    steps = np.diff(f[lo:hi + 1])
    bad = int((steps <= 0).sum())
    if bad:
        f[lo:hi + 1] = np.maximum.accumulate(f[lo:hi + 1])
    return f, bad


def tie_bands_to_reference(tables: np.ndarray, ref_g: np.ndarray, Z: np.ndarray,
                           D: np.ndarray | None, level_w: np.ndarray) -> tuple[np.ndarray, dict]:
    """Per-band curves on the scale (and constant) of a shared reference curve.

    Each band of a per-band curve has its own scale that the data do not fix (``f → s·f``
    with ``E → s·E``): the gauge ``g(Z_mid) = ln Z_mid`` fixed it at a level that a dark
    band's samples never reach, i.e. by the smoothness prior's extrapolation. Under the
    premise of the gauge — one non-linearity common to all bands — the shared curve
    ``ref_g`` (all bands pooled) is that non-linearity, and each band is mapped onto it
    over the levels its own samples cover; outside them (no data) the band follows the
    reference's shape, joined continuously in the log domain.

    Parameters
    ----------
    tables
        ``(C, L)``: with ``D``, the dark-offset model's linear-domain tables ``f`` (scale
        and constant free: fitted as ``f ≈ s·F + k``, ``F = exp ref_g``); without, log
        curves ``g`` (scale free: fitted as ``g ≈ ref_g + ln s``).
    ref_g
        ``(L,)`` the shared curve's ``g``.
    Z, D
        ``(N, P, C)`` the band curves' samples (levels) and their raw darks (or None).
    level_w
        ``(L,)`` the level weighting: the samples it gives weight are the data.

    Returns
    -------
    ``g`` float64 ``(C, L)`` and ``{"bands_from_reference": count}``: bands whose samples
    could not be fitted (fewer than two levels, or a fitted scale ≤ 0), which take the
    reference curve as it is.
    """
    C, L = tables.shape
    lev = np.arange(L)
    ref_g = np.asarray(ref_g, dtype=np.float64)
    use = level_w[Z] > 0
    if D is not None:
        use &= Z > np.ceil(D)
    use &= use.sum(axis=1, keepdims=True) >= 2            # one exposure ties no levels
    ch = np.broadcast_to(np.arange(C), Z.shape)
    counts = np.bincount((ch * L + Z)[use], minlength=C * L).reshape(C, L).astype(np.float64)
    seen = counts > 0
    ok = seen.sum(axis=1) >= 2
    lo = np.where(ok, np.argmax(seen, axis=1), 0)
    hi = np.where(ok, L - 1 - np.argmax(seen[:, ::-1], axis=1), L - 1)
    if D is not None:
        # the merge evaluates f at the dark level itself: part of the band's range
        lo = np.minimum(lo, np.floor(D.min(axis=(0, 1))).astype(np.intp))
        F = np.exp(ref_g)
        # residuals in levels (÷ the slope): no part of the range dominates by its scale
        w = counts / np.maximum(np.gradient(F), 1e-12 * F.max()) ** 2
        x, y = F[None, :], np.asarray(tables, dtype=np.float64)
    else:
        w = counts
        x, y = ref_g[None, :], np.asarray(tables, dtype=np.float64)
    W = np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    mx = (w * x).sum(axis=1, keepdims=True) / W
    my = (w * y).sum(axis=1, keepdims=True) / W
    if D is not None:
        s = (w * (x - mx) * (y - my)).sum(axis=1) / np.maximum(
            (w * (x - mx) ** 2).sum(axis=1), 1e-300)
        ok &= np.isfinite(s) & (s > 0)
        s = np.where(ok, s, 1.0)
        h = (y - (my[:, 0] - s * mx[:, 0])[:, None]) / s[:, None]
        # a level of the band's range where the fitted table is not above 0 (noise at
        # the dark end) cannot be logged: floored far below one DN of the reference
        g = np.log(np.maximum(h, 1e-6 * F[L // 2]))
    else:
        g = y - (my - mx)
    inside = (lev >= lo[:, None]) & (lev <= hi[:, None])
    d_lo = np.take_along_axis(g, lo[:, None], axis=1) - ref_g[lo][:, None]
    d_hi = np.take_along_axis(g, hi[:, None], axis=1) - ref_g[hi][:, None]
    g = np.where(inside, g, ref_g[None, :] + np.where(lev[None, :] < lo[:, None], d_lo, d_hi))
    g[~ok] = ref_g
    return g, {"bands_from_reference": int((~ok).sum())}


def match_constant(f: np.ndarray, plain, zmin: int, parameters: dict,
                   zmax: int | None = None):
    """The curve ``g = ln(f − c)`` of a linear-domain table ``f`` (C, L) whose additive
    constant is free, with ``c`` chosen so that ``g`` follows ``plain``.

    ``plain`` (Debevec–Malik without the offset) is accurate over the
    well-exposed levels ``L/8 … 0.9·L``, where the offset is negligible; the
    constant ``c`` that makes ``ln(f − c)`` parallel to it there is kept,
    subject to ``f − c > 0`` at every level — with ``f`` continued as a straight line
    below ``zmin`` (the lowest level seen) and kept from falling above it — so that
    ``exp g`` is that continuation everywhere and the merge's ``f(Z) − f(D)`` never
    meets a floor. The result has the gauge ``g(Z_mid) = ln Z_mid``.

    ``zmax``: the highest level a pair of exposures ties
    (:func:`mehs.synthesis.response_extend.covered_top`; None: every level). The constant
    is fitted on the levels up to it only — above it both curves are extrapolations — and
    the result is continued above it as a power law
    (:func:`~mehs.synthesis.response_extend.extend_power_law`). A bracket whose pairs stop
    at level 470 (a dark chart, a window seen by one exposure) had its constant fitted on
    L/8…0.9·L, all extrapolated.

    (The constraint used to be ``0.98·min f`` from ``zmin`` up, which is the bound
    ``plain`` always pushed ``c`` to: ``f − c`` was 2 % of ``f(zmin)`` there — and
    negative where the direct solve's ``f`` is, below the dark level — so every level
    at or below the lowest sampled one was floored to ~0, clipping the signed samples
    of dark pixels the rest of the image reaches. Its minimum also ran over levels no
    sample covers: a table falling there (to −1e23) made the curve flat.)
    """
    L = plain.levels
    f = np.asarray(f, dtype=np.float64)
    g0 = plain.table(None if plain.shared else f.shape[0])
    if g0.shape[0] != f.shape[0]:
        g0 = np.broadcast_to(g0, f.shape)
    zmin = int(min(max(zmin, 0), L - 2))
    lev = np.arange(L)
    # no level above the lowest seen maps to less signal; below it, a straight line with
    # the low end's mean slope (a few levels: the lowest one alone is noise)
    f = f.copy()
    f[:, zmin:] = np.maximum.accumulate(f[:, zmin:], axis=1)
    k = max(1, min(8, L - 1 - zmin))
    mid = max(L // 2, zmin + 1)
    rise = (f[:, mid] - f[:, zmin]) / (mid - zmin)
    slope = np.maximum((f[:, zmin + k] - f[:, zmin]) / k, 1e-3 * np.maximum(rise, 1e-300))
    f[:, :zmin] = f[:, zmin:zmin + 1] - slope[:, None] * (zmin - lev[:zmin])
    top = int(0.9 * L) if zmax is None else min(int(0.9 * L), int(zmax))
    zs = np.arange(L // 8, top, 16)
    if zs.size < 8:     # pairs end below L/8: the covered upper half
        zs = np.unique(np.linspace(max(zmin, top // 2), max(top, zmin + 1), 32).astype(np.intp))
    # one level's rise of headroom at level 0: exp g never reaches 0 on the table
    cmax = f[:, 0] - slope
    cmin = np.minimum(-0.5 * f[:, L // 2], cmax - (f[:, L // 2] - f[:, 0]))
    frac = np.linspace(0.0, 1.0, 301)
    c = cmin[:, None] + (cmax - cmin)[:, None] * frac[None, :]          # (C, K)
    lg = np.log(np.maximum(f[:, None, zs] - c[:, :, None], 1e-12))      # (C, K, Z)
    d = lg - g0[:, None, zs]
    err = d.var(axis=2)
    best = c[np.arange(c.shape[0]), np.argmin(err, axis=1)]
    f2 = np.maximum(f - best[:, None], 1e-12 * np.maximum(f[:, -1] - best, 1e-300)[:, None])
    g2 = np.log(f2)
    if zmax is not None:
        from mehs.synthesis.response_extend import extend_power_law

        g2 = extend_power_law(g2, int(zmax))
    g2 += np.log(L // 2) - g2[:, L // 2:L // 2 + 1]
    params = dict(parameters)
    params["offset_constant"] = best.tolist() if best.size > 1 else float(best[0])
    from mehs.synthesis.response import ResponseCurve

    return ResponseCurve(g2[0] if plain.shared else g2, plain.bit_depth, method=plain.method,
                         smoothness=plain.smoothness, weighting=plain.weighting,
                         wavelengths=plain.wavelengths, parameters=params)
