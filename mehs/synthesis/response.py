"""Camera response curves: Debevec–Malik recovery, a linear fallback, save/load.

A response curve maps a (dark-subtracted) sensor level ``z`` to the log
exposure ``g(z) = ln(E·Δt)``. It is one curve shared by all bands (one
sensor, one ADC) or one curve per band.

Gauge
-----
Debevec & Malik fix the free constant by ``g(Z_mid) = 0``. mehs fixes
``g(Z_mid) = ln(Z_mid)`` instead — the same solution shifted by the constant
``ln Z_mid`` for every band — so that a linear sensor's recovered curve is
``ln z`` and merged radiance comes out in DN per ms whichever merge method or
curve is used. The constant is the same for every band, so spectral shapes are
preserved by per-band curves when the sensor non-linearity is common to all
bands.

Smoothness
----------
``smoothness`` (λ) is made independent of the bit depth and the sample count:
the penalty is ``λ·ρ·((L−1)/255)⁴·Σ_z [w(z) g''(z)]²`` with ``ρ = N·P/L``
samples per level, so λ = 10 at 8 bits with ρ ≈ 1 is the λ of Debevec & Malik's objective
(their eq. 3). Their ``gsolve`` code and OpenCV's ``CalibrateDebevec`` multiply the smoothness
*rows* by λ, so theirs enters squared: OpenCV's ``lambda`` = √λ (λ = 10 here is OpenCV's
3.16, OpenCV's default 10 is λ = 100 here). The default is :data:`DEFAULT_SMOOTHNESS`
(λ = 100; see there for the grid measured on it).

References
----------
- Debevec, P. E. and Malik, J. (1997). Recovering high dynamic range radiance
  maps from photographs. SIGGRAPH 97, 369–378.
- Robertson, M. A., Borman, S. and Stevenson, R. L. (2003). Estimation-theoretic
  approach to dynamic range enhancement using multiple exposures. JEI 12(2).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mehs.errors import InputError
# the curve type and its file format live in response_curve (split for size); re-exported
from mehs.synthesis.response_curve import FORMAT, ResponseCurve, _check_bit_depth
from mehs.threadwarn import local_filter

_REEXPORTED = (FORMAT, ResponseCurve)    # importable from here as before the split


#: Default smoothness λ (module docstring for its normalisation). Chosen against the
#: simulator's true curve on 20 shared-curve brackets (64² px, 204 bands; colorchecker, lamp
#: and natural scenes; linear, gamma 0.5/0.8, s-curve sensors; 3 exposures ×4/×8, 5 and 7
#: ×4; 10/12/14 bits; 3 seeds; dark brackets at 10⁻³ of the light), scoring the merged
#: radiance against the true curve's merge of the same data (median |ratio − 1| and the
#: ptp of its brightness-decile bias). λ = 100 (the earlier default, set before the
#: black-level offset rounds reached their fixed point) leaves that fixed point wiggling:
#: ±1.5 % across deciles on gamma sensors (bench_synthesis's accuracy scene: median SAM
#: 0.985°, rel. error 0.0151, against the true curve's 0.752° / 0.0101). Median over the
#: bright gamma/linear brackets, λ = 30 / 100 / 300 / 1000: rel 0.88 / 0.71 / 0.45 / 0.12 %,
#: decile ptp 3.5 / 2.6 / 1.5 / 0.7 %. A stiffer prior bends what has real curvature:
#: an s-curve's knee (brightest decile +2.9 → +4.0 → +4.4 %, ptp 3.4 / 4.8 / 5.2 %) and dark
#: brackets (longest exposure's p90 signal < L/16: ptp 1.5 / 6.4 / 13.5 %, lamp ×10⁻³,
#: gamma). λ = 300 would take most of the gain on gamma sensors, but it broke 6 existing
#: tests (dark shared/per-band brackets, the wide-bracket and too-little-data flags, a film
#: bracket): the default stays 100, and a shared curve of a bright bracket chooses among
#: :data:`SMOOTHNESS_CANDIDATES` from its data. The bench_synthesis accuracy scene
#: at λ = 300: SAM 0.811°, rel 0.0113 (1000: 0.760°, 0.0103). The grid is
#: ``benchmarks/bench_response.py --smoothness 100,300,1000``.
DEFAULT_SMOOTHNESS = 100.0
#: λ a shared curve of a bright bracket may take when none is given (``smoothness=None``,
#: :func:`mehs.synthesis.fuse_response.recover_response`): the rounds converge at
#: :data:`DEFAULT_SMOOTHNESS`, continue :data:`SMOOTHNESS_ROUNDS` rounds at each larger λ,
#: and the largest λ whose held-out offset misfit stays within :data:`SMOOTHNESS_TOLERANCE`
#: of the default's is kept (:func:`mehs.synthesis.response_select.pick_smoothness`).
SMOOTHNESS_CANDIDATES = (100.0, 300.0, 1000.0)
#: rounds run at each candidate λ from the default's fixed point (15: 8 left the stiffer
#: curves' misfit in transit, +1.5…+2.8 % on gamma brackets where 15 gave +1.1…+1.7 %)
SMOOTHNESS_ROUNDS = 15
#: Relative rise of the held-out misfit over the default λ's that a stiffer λ may cost. On
#: 48² brackets (51 bands) λ = 300 raised it by −0.5…+2.7 % where its radiance was closer to
#: the true curve's merge (gamma 0.5/0.8 sensors, 3 × ×4 and 7 × ×4) and by +6.4…+17 %
#: where it bent real curvature (s-curve knees, a linear sensor's ln z); dark brackets
#: (+2.0 %, worse) keep the default (:func:`mehs.synthesis.response_select.is_dark`).
SMOOTHNESS_TOLERANCE = 0.03


# ------------------------------------------------------------------ weighting
def weight_hat(levels: int) -> np.ndarray:
    """Debevec's hat ``w(z) = min(z, L−1−z)``, normalised to a peak of 1. Shape (L,)."""
    z = np.arange(levels, dtype=np.float64)
    return np.minimum(z, levels - 1 - z) / ((levels - 1) / 2.0)


def weight_gaussian(levels: int) -> np.ndarray:
    """Robertson et al.'s Gaussian-like ``exp(−4 (z−mid)²/mid²)``, ends set to 0. Shape (L,)."""
    z = np.arange(levels, dtype=np.float64)
    mid = (levels - 1) / 2.0
    w = np.exp(-4.0 * (z - mid) ** 2 / mid ** 2)
    w[[0, -1]] = 0.0
    return w


def weight_uniform(levels: int) -> np.ndarray:
    """Equal weights except the two clipped end levels. Shape (L,)."""
    w = np.ones(levels)
    w[[0, -1]] = 0.0
    return w


WEIGHTINGS: dict[str, Callable[[int], np.ndarray]] = {
    "hat": weight_hat, "gaussian": weight_gaussian, "uniform": weight_uniform}


def weighting_table(weighting: str | Callable, levels: int) -> np.ndarray:
    """Weights of every level, float64 (L,), for a named or callable weighting.

    A callable gets the level vector ``arange(L)`` and returns non-negative
    weights. The end levels 0 and L−1 are always given weight 0: they hold
    clipped samples (below black after dark subtraction, or saturated).
    """
    if callable(weighting):
        w = np.asarray(weighting(np.arange(levels)), dtype=np.float64).reshape(-1)
        if w.shape != (levels,):
            raise InputError(f"weighting callable returned {w.shape}, expected ({levels},)")
    elif weighting in WEIGHTINGS:
        w = WEIGHTINGS[weighting](levels)
    else:
        raise InputError(f"unknown weighting {weighting!r}; use one of {sorted(WEIGHTINGS)} "
                         "or a callable")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError("weights must be finite and non-negative")
    w = w.copy()
    w[[0, -1]] = 0.0
    if not np.any(w > 0):
        raise InputError("the weighting gives zero weight to every level")
    return w


# ------------------------------------------------------------------ sampling
def to_levels(raw: np.ndarray, dark: np.ndarray | float | None, bit_depth: int,
              saturation: float | np.ndarray | None = None) -> np.ndarray:
    """Dark-subtracted integer levels for the response solve, int32.

    ``raw − dark`` rounded and clipped to 0..L−2; samples with ``raw ≥
    saturation`` (raw DN; default L−1) become level L−1, which every weighting
    gives zero weight.
    """
    L = 1 << bit_depth
    raw = np.asarray(raw)
    sat = L - 1 if saturation is None else saturation
    x = raw.astype(np.float32)
    if dark is not None:
        x = x - np.asarray(dark, dtype=np.float32)
    z = np.clip(np.rint(x), 0, L - 2).astype(np.int32)
    z[raw >= sat] = L - 1
    return z


def sample_pixels(stack: np.ndarray, n: int | None = None, *, seed: int | None = 0,
                  bit_depth: int = 12, strata: int = 64,
                  max_candidates: int | None = None, return_index: bool = False):
    """Stratified sample of pixel levels for the Debevec–Malik solve.

    Parameters
    ----------
    stack
        Integer levels of shape ``(P, pixels)`` or ``(P, pixels, C)`` — or
        ``(P, lines, samples[, C])`` when ``C`` is given as a 4-D array —
        dark-subtracted, with saturated samples at L−1 (see :func:`to_levels`).
    n
        Pixels per channel; default ``⌈2·L/(P−1)⌉``.
    seed
        Seed of the random visiting order (deterministic sampling).
    strata
        Intensity strata per exposure: pixels are kept while one of their
        exposures falls in an under-filled (exposure, stratum) cell, so every
        part of the range and every exposure is represented.

    Returns
    -------
    int32 ``(n, P, C)`` (or ``(n, P)`` for a 2-D ``stack``): the sampled levels;
    with ``return_index`` also the int64 ``(C, n)`` pixel indices into ``stack``.

    Raises
    ------
    InputError
        When ``n·(P−1) ≤ L`` (the system would be underdetermined) or when
        fewer than ``n`` pixels have two usable exposures in some channel.
    """
    from mehs.synthesis._kernels import stratified_pick

    st = np.asarray(stack)
    squeeze = False
    if st.ndim == 2:
        st = st[:, :, None]
        squeeze = True
    elif st.ndim == 4:
        st = st.reshape(st.shape[0], -1, st.shape[3])
    elif st.ndim != 3:
        raise InputError(f"stack must be (P, pixels[, C]), got shape {st.shape}")
    P, M, C = st.shape
    if P < 2:
        raise InputError(f"response recovery needs at least 2 exposures, got {P}")
    L = 1 << _check_bit_depth(bit_depth)
    if n is None:
        n = int(np.ceil(2.0 * L / (P - 1)))
    n = int(n)
    if n * (P - 1) <= L:
        raise InputError(f"{n} pixels × ({P}−1) exposures = {n * (P - 1)} equations do not "
                         f"exceed the {L} levels of a {bit_depth}-bit curve; sample more pixels "
                         "(or share one curve across bands)")
    rng = np.random.default_rng(seed)
    order = rng.permutation(M)
    if max_candidates is not None and M > max_candidates:
        order = order[:max_candidates]
    idx = stratified_pick(np.ascontiguousarray(st, dtype=np.int32), order.astype(np.int64),
                          n, int(strata), L)
    short = np.flatnonzero(idx[:, -1] < 0)
    if short.size:
        got = int((idx[short[0]] >= 0).sum())
        raise InputError(f"only {got} pixels with two or more usable exposures in channel "
                         f"{int(short[0])}; {n} needed for a {bit_depth}-bit curve "
                         f"with {P} exposures")
    # (C, n) indices → (n, P, C) levels
    Z = np.take_along_axis(st.transpose(2, 1, 0), idx[:, :, None], axis=1)  # (C, n, P)
    Z = np.ascontiguousarray(Z.transpose(1, 2, 0))
    Z = Z[:, :, 0] if squeeze else Z
    return (Z, idx) if return_index else Z


# ---------------------------------------------------------------- recovery
def recover_response_Debevec1997(samples: np.ndarray, log_times: np.ndarray, *,
                                 bit_depth: int = 12, smoothness: float = DEFAULT_SMOOTHNESS,
                                 weighting: str | Callable = "hat", shared: bool = False,
                                 solver: str = "pcg", tol: float = 1e-10,
                                 maxiter: int = 5000, wavelengths: np.ndarray | None = None,
                                 parameters: dict | None = None) -> ResponseCurve:
    """Recover ``g`` by Debevec & Malik's weighted, smoothed least squares.

    Minimises ``Σ_i Σ_j {w(Z_ij)[g(Z_ij) − ln E_i − ln Δt_j]}² + λ' Σ_z [w(z) g''(z)]²``
    with the gauge ``g(Z_mid) = ln Z_mid`` (module docstring).

    Parameters
    ----------
    samples
        Integer levels ``(N, P)`` (one channel) or ``(N, P, C)``; level L−1
        marks a saturated sample (weight 0).
    log_times
        ``ln Δt_j``, shape ``(P,)``; or one effective log time per sample,
        ``(N, P)`` / ``(N, P, C)`` — :func:`mehs.synthesis.fuse.recover_response`
        passes ``ln(Δt_j + B_ij/E_i)`` so that an offset ``B`` (black level, dark
        current) added *before* the non-linearity fits the model.
    smoothness
        λ, normalised as described in the module docstring.
    weighting
        ``"hat"`` (Debevec), ``"gaussian"``, ``"uniform"`` or a callable of the levels.
    shared
        One curve for all C channels (their samples are pooled) instead of one each.
    solver
        ``"pcg"``: ln E eliminated exactly (Schur complement), the L×L system
        solved by CG preconditioned with its pentadiagonal part (numba, parallel
        over channels); ``"direct"``: the same Schur complement built with
        scipy.sparse and factorised by SuperLU (reference; slower).

    Returns
    -------
    ResponseCurve
        ``g`` float64 ``(L,)`` if ``shared`` or one channel, else ``(C, L)``.
    """
    L = 1 << _check_bit_depth(bit_depth)
    Z = np.asarray(samples)
    if Z.ndim == 2:
        Z = Z[:, :, None]
    if Z.ndim != 3:
        raise InputError(f"samples must be (N, P) or (N, P, C), got shape {Z.shape}")
    if not np.issubdtype(Z.dtype, np.integer):
        raise InputError(f"samples must be integer levels, got dtype {Z.dtype}")
    N, P, C = Z.shape
    lt_all = np.asarray(log_times, dtype=np.float64)
    per_sample = lt_all.ndim > 1
    if P < 2:
        raise InputError(f"response recovery needs at least 2 exposures, got {P}")
    if per_sample:
        lt_all = lt_all.reshape(lt_all.shape + (1,) * (3 - lt_all.ndim))
        if lt_all.shape[:2] != (N, P) or lt_all.shape[2] not in (1, C):
            raise InputError(f"per-sample log times must have shape ({N}, {P}[, {C}]), "
                             f"got {np.shape(log_times)}")
        lt_all = np.broadcast_to(lt_all, (N, P, C))
        lt = np.median(lt_all.reshape(-1, P), axis=0)
    else:
        lt = lt_all.reshape(-1)
    if lt.size != P:
        raise InputError(f"{lt.size} log exposure times for {P} exposures")
    if not np.all(np.isfinite(lt_all)):
        raise InputError("log exposure times must be finite")
    if not per_sample and np.unique(lt).size != P:
        raise InputError("exposure times must be distinct")
    if Z.min() < 0 or Z.max() > L - 1:
        raise InputError(f"levels must lie in 0..{L - 1} for {bit_depth} bits "
                         f"(got {Z.min()}..{Z.max()})")
    if not (np.isfinite(smoothness) and smoothness > 0):
        # the end levels (weight 0) and any level no sample hits are tied to the
        # curve only by the smoothness term: at λ = 0 they are left at the gauge value
        raise InputError(f"smoothness (lambda) must be finite and > 0, got {smoothness}")
    w = weighting_table(weighting, L)
    if shared and C > 1:
        Zc = Z.transpose(1, 0, 2).reshape(P, N * C).T[None]      # (1, N·C, P)
        LTc = lt_all.transpose(1, 0, 2).reshape(P, N * C).T[None] if per_sample else None
    else:
        Zc = Z.transpose(2, 0, 1)                                # (C, N, P)
        LTc = lt_all.transpose(2, 0, 1) if per_sample else None
    Zc = np.ascontiguousarray(Zc, dtype=np.int32)
    LTc = (np.ascontiguousarray(LTc, dtype=np.float64) if per_sample
           else np.ascontiguousarray(lt.reshape(1, 1, P)))
    wz = w[Zc]
    # only pixels with two weighted exposures tie levels together; the others
    # (saturated or black in all but one exposure, unfilled sample slots) add no
    # equation, and with none at all the solve returns a flat curve
    n_eff = int(((wz > 0).sum(axis=2) >= 2).sum(axis=1).min())
    if n_eff * (P - 1) <= L:
        raise InputError(f"{n_eff} pixels with two or more usable (unsaturated, above-black) "
                         f"exposures × ({P}−1) do not exceed the {L} levels of a "
                         f"{bit_depth}-bit curve; the bracket cannot determine the response")
    mid = L // 2
    rho = Zc.shape[1] * P / L
    lam_eff = smoothness * rho * ((L - 1) / 255.0) ** 4
    lam = np.full(Zc.shape[0], lam_eff)
    # A floor on the smoothness weights keeps the end levels tied to the curve.
    wsm = np.maximum(w, 1e-3)
    if solver == "pcg":
        from mehs.synthesis._kernels import debevec_pcg

        g, iters, relres = debevec_pcg(Zc, wz, LTc, wsm, lam, mid, float(tol), int(maxiter))
        bad = np.flatnonzero(relres > max(tol * 1e3, 1e-6))
        for ch in bad:   # rare: fall back to the direct factorisation for that channel
            g[ch] = _solve_direct(Zc[ch], wz[ch], LTc[min(ch, LTc.shape[0] - 1)], wsm, lam_eff, mid)
        stats = {"solver": "pcg", "iterations_max": int(iters.max()),
                 "iterations_mean": float(iters.mean()), "direct_fallbacks": int(bad.size)}
    elif solver == "direct":
        g = np.stack([_solve_direct(Zc[ch], wz[ch], LTc[min(ch, LTc.shape[0] - 1)], wsm, lam_eff,
                                    mid) for ch in range(Zc.shape[0])])
        stats = {"solver": "direct"}
    else:
        raise InputError(f"unknown solver {solver!r}; use 'pcg' or 'direct'")
    # above the highest level a pair of exposures ties, g is the prior's straight line in z
    # (an exponential f): continued as a power law instead (response_extend)
    from mehs.synthesis.response_extend import covered_top, extend_power_law

    hi = covered_top(Zc.transpose(1, 2, 0), w, per_channel=True)
    g = extend_power_law(g, hi, gauge=mid) + np.log(mid)
    g = g[0] if g.shape[0] == 1 else g
    params = {"samples": int(N), "exposures": int(P), "log_times": lt.tolist(),
              "gauge_level": mid, "smoothness_effective": lam_eff,
              "covered_top_level": int(hi.max()), **stats,
              **(parameters or {})}
    return ResponseCurve(g, bit_depth, method="debevec1997", smoothness=float(smoothness),
                         weighting=weighting if isinstance(weighting, str) else "custom",
                         wavelengths=None if g.ndim == 1 else wavelengths, parameters=params)


def _solve_direct(Z: np.ndarray, wz: np.ndarray, lt: np.ndarray, wsm: np.ndarray,
                  lam: float, mid: int) -> np.ndarray:
    """The Schur-complement system of one channel, sparse LU (SuperLU). Returns g (L,), g[mid] = 0."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    L = wsm.size
    N, P = Z.shape
    w2 = wz * wz
    W = w2.sum(1)
    ok = W > 0
    Winv = np.where(ok, 1.0 / np.where(ok, W, 1.0), 0.0)
    rows = np.repeat(np.arange(N), P)
    U = sp.csr_matrix((w2.ravel(), (rows, Z.ravel())), shape=(N, L))
    c = np.asarray(U.sum(0)).ravel()
    D2 = sp.diags([np.ones(L - 2), -2 * np.ones(L - 2), np.ones(L - 2)], [0, 1, 2],
                  shape=(L - 2, L))
    S = sp.diags(c) + lam * (D2.T @ sp.diags(wsm[1:-1] ** 2) @ D2) - U.T @ sp.diags(Winv) @ U
    lt = np.broadcast_to(lt.reshape(-1, lt.shape[-1]), (N, P))    # (1, P) or (N, P)
    m = (w2 * lt).sum(1) * Winv
    b = np.bincount(Z.ravel(), weights=(w2 * (lt - m[:, None])).ravel(), minlength=L)
    keep = np.arange(L) != mid
    S = S.tocsr()[keep][:, keep].tocsc()
    # (a singular system shows as non-finite values, checked below; this thread only)
    with local_filter("ignore"):
        x = spla.spsolve(S, b[keep])
    g = np.zeros(L)
    g[keep] = x
    if not np.all(np.isfinite(g)):
        raise InputError("the response system is singular: the samples do not tie the "
                         "levels together (too few overlapping exposures?)")
    return g
