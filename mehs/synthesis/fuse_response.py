"""Which response curve a fusion uses: the linearity test, Debevec–Malik recovery on raw
levels, and the recovered curve's self-consistency check (:func:`choose_response`).

``response="auto"`` (the default of ``mehs fuse``) first asks whether consecutive
exposures agree with a linear sensor (:func:`mehs.synthesis.noise.linearity_PTC`, on
the photon-transfer statistics that the noise model then reuses); only when they do
not, or the test cannot tell, is a curve recovered and checked
(:mod:`mehs.synthesis.response_check`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.synthesis._numba_start import skip_scipy_linalg_import
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.merge import warm_merge_kernel
from mehs.synthesis.response import (DEFAULT_SMOOTHNESS, SMOOTHNESS_CANDIDATES,
                                     SMOOTHNESS_ROUNDS, ResponseCurve,
                                     recover_response_Debevec1997, sample_pixels, to_levels,
                                     weighting_table)
from mehs.synthesis.response_solves import _offset_direct, _offset_rounds

#: "auto" uses the linear curve while consecutive exposures agree with it within this
#: relative error at every well-exposed signal level
LINEARITY_TOLERANCE = 0.02


class ResponseUndeterminedWarning(UserWarning):
    """A recovered response curve is not determined by its bracket (see :mod:`~mehs.synthesis.response_check`)."""


def check_recovered_response(bracket: Bracket, curve: ResponseCurve, *, smoothness: float,
                             samples: int | None, seed: int, shared: bool,
                             saturation: np.ndarray, probe=None) -> dict[str, Any]:
    """Run :func:`mehs.synthesis.response_check.response_uncertainty` on a curve recovered
    by :func:`recover_response` (raw levels) from ``bracket``, and
    :func:`exposure_consistency` (on ``probe``, the bracket's default probe, when given)."""
    from mehs.synthesis.response_check import response_uncertainty

    # the solve that made a shared curve (offset="auto" kept one of two) is what is checked,
    # at one solve per re-recovery instead of two
    offset = curve.parameters.get("offset") if curve.shared else None
    # a λ chosen from the data continued the default λ's rounds: re-recovered the same way
    # (fresh rounds at that λ reach another curve, 1.6 % away on a lamp bracket, 3 × ×4,
    # which the check read as the curve's uncertainty)
    choice = curve.parameters.get("smoothness_choice") if offset == "rounds" else None
    warm = DEFAULT_SMOOTHNESS if choice and choice.get("chosen") != DEFAULT_SMOOTHNESS else None

    def again(*, smoothness: float, pool):
        return recover_response(bracket, smoothness=smoothness, samples=samples, seed=seed,
                                shared=shared, levels="raw", saturation=saturation, pool=pool,
                                offset=offset if offset in ("direct", "rounds") else "auto",
                                warm_from=warm)

    from mehs.synthesis.merge import merge_bracket

    nl, ns, nb = bracket.shape
    rows = np.unique(np.linspace(0, nl - 1, min(nl, 64)).round().astype(np.intp))

    def rows_of(data) -> np.ndarray:
        """``data[rows]`` with the memory layout and writeability of ``data``: the merge
        kernel then runs the specialisation the full cube compiles (a writeable copy of
        a read-only memory map compiled a second one, ~15 s on a first-ever run)."""
        a = np.asarray(data)
        out = np.empty_like(a[:rows.size], order="K")
        out[...] = a[rows]
        out.flags.writeable = a.flags.writeable
        return out

    subset = [rows_of(e.data) for e in bracket.exposures]

    def merge(c: ResponseCurve):
        mr = merge_bracket(subset,
                           bracket.times_ms, method="poisson", response=c, darks=bracket.darks,
                           bit_depth=bracket.bit_depth, saturation=saturation,
                           consistency=False, source=bracket.source)
        usable = np.broadcast_to((mr.mask == 0)[..., None], mr.radiance.shape)
        return np.asarray(mr.radiance, dtype=np.float64), usable

    try:
        out = response_uncertainty(again, merge, curve, shape=(nl, ns), smoothness=smoothness)
    except InputError as exc:   # a half-bracket too small to recover on its own
        return {"determined": False, "median": None, "p95": None,
                "reason": f"check impossible ({exc.problem})"}
    out.update(exposure_consistency(bracket, curve, saturation, probe=probe))
    dev = out["exposure_consistency"]
    if out["determined"] and dev is not None and dev > CONSISTENCY_TOLERANCE:
        out["determined"] = False
        out["reason"] = (f"consecutive exposures linearised by the curve disagree by {dev:.1%} "
                         f"(p75 over signal levels, > {CONSISTENCY_TOLERANCE:.0%})")
        from mehs.synthesis.response_check import ADVICE

        out["advice"] = ADVICE
    from mehs.synthesis.response_check import coverage_verdict

    coverage_verdict(out, subset, bracket.darks, saturation,
                     curve.parameters.get("covered_top_level"))
    return out


#: Largest p75 disagreement of consecutive exposures, linearised by a recovered curve, that
#: the check accepts: 1.5× the linear curve's tolerance (a recovered curve's own ripple).
#: Split halves and λ vs 10λ share a curve's bias and cannot see it; this can (a gamma
#: sensor's curve after 12 offset rounds: 8.9 %, radiance −10…+2.6 % of the truth).
CONSISTENCY_TOLERANCE = 0.03


def exposure_consistency(bracket: Bracket, curve: ResponseCurve,
                         saturation: np.ndarray, probe=None) -> dict[str, Any]:
    """``Σy_k/(r·Σy_j)`` of consecutive exposures linearised by ``curve`` (the merge's own
    linearisation), per signal level — the linearity test of ``response="auto"`` applied to
    a recovered curve: ``exposure_consistency`` (p75 of |ratio − 1|, noise removed) and its
    ``exposure_consistency_resolution``; None when no level is seen by two exposures.
    ``probe``: :func:`mehs.synthesis.noise.probe_bracket`'s default probe of the bracket,
    if already read."""
    from mehs.synthesis.fuse import _lineariser
    from mehs.synthesis.noise import linearity_PTC, probe_bracket

    probe = probe if probe is not None else probe_bracket(bracket, saturation)
    lin = _lineariser(curve, "linear", bracket.bit_depth,
                      has_dark=[d is not None for d in bracket.darks])
    try:
        r = linearity_PTC(probe, lin, bit_depth=bracket.bit_depth)
    except InputError:
        return {"exposure_consistency": None, "exposure_consistency_resolution": None}
    return {"exposure_consistency": float(r["deviation"]),
            "exposure_consistency_resolution": float(r["resolution"])}


def _candidate_levels(bracket: Bracket, n_candidates: int, seed: int, saturation: np.ndarray,
                      subtract_dark: bool, pool: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """int32 (P, M, bands) levels of M random pixels (memmaps read only there), and
    float32 (P, M, bands) the raw dark level of each (0 where none or subtracted).

    ``pool``: flat pixel indices to draw from (default every pixel); disjoint pools
    give independent curves for the self-consistency check.
    """
    nl, ns, nb = bracket.shape
    rng = np.random.default_rng(seed)
    pool = np.arange(nl * ns) if pool is None else np.asarray(pool, dtype=np.int64)
    m = min(pool.size, n_candidates)
    flat = np.sort(rng.choice(pool, size=m, replace=False))
    rows, cols = np.divmod(flat, ns)
    out = np.empty((len(bracket.exposures), m, nb), dtype=np.int32)
    darks = np.zeros((len(bracket.exposures), m, nb), dtype=np.float32)
    for j, e in enumerate(bracket.exposures):
        raw = np.asarray(e.data[rows, cols], dtype=np.float32)
        dk = bracket.darks[j][cols] if bracket.darks[j] is not None else None
        out[j] = to_levels(raw, dk if subtract_dark else None, bracket.bit_depth,
                           saturation[None, :])
        if dk is not None and not subtract_dark:
            darks[j] = dk
    return out, darks


def recover_response(bracket: Bracket, *, smoothness: float | None = None,
                     samples: int | None = None,
                     seed: int = 0, shared: bool = False, levels: str = "raw",
                     saturation: np.ndarray | None = None,
                     weighting: str = "hat", offset: str = "auto",
                     offset_iterations: int | None = None,
                     pool: np.ndarray | None = None,
                     warm_from: float | None = None) -> ResponseCurve:
    """Debevec–Malik curve(s) of a bracket, sampled stratified from its exposures.

    ``levels="raw"`` fits the curve to raw DN (the black level then passes
    through the non-linearity, as on most sensors; the merge subtracts the
    *linearised* dark); ``"dark-subtracted"`` fits it to ``raw − dark``.

    With raw levels, Debevec and Malik's model ``g(Z_ij) = ln E_i + ln Δt_j``
    misses the offset ``B_j`` (black level plus dark current, which grows with
    ``Δt``) that is added before the non-linearity: the curve bends near black
    (by a factor 2 for a gamma-0.8 sensor), and dark pixels of different
    exposures disagree. With a dark reference for every exposure the model that
    holds, ``f(Z_ij) − f(D_ij) = E_i·Δt_j`` (``f = exp g``, ``D_ij`` the raw dark of the
    sample's column), is solved in one of two ways (``offset``):

    - ``"direct"``: one linear least-squares solve in the linear domain of ``f``
      (:func:`mehs.synthesis.response_offset.solve_offset_response`, the plain
      Debevec–Malik curve as pilot of its noise weights);
    - ``"rounds"`` (shared curves only): ``offset_iterations`` rounds (None:
      :data:`~mehs.synthesis.response_solves.OFFSET_ITERATIONS_SHARED`) re-solve with
      per-sample effective times ``ln(Δt_j + B_ij/E_i)`` — ``B_ij = exp(g(dark_ij))``,
      ``E_i`` the pixel's current estimate — whose fixed point is the same model;
    - ``"auto"`` (default): direct for per-band curves; for a shared curve the rounds, but
      on a dark bracket both, keeping the one whose residual on held-out pixels is smaller
      (:mod:`mehs.synthesis.response_select`: there either alone was 15–55 % off the true
      curve's radiance in some brightness decile).

    A per-band curve (``shared=False``) is solved with the shared curve of the same
    bracket as its pilot and as the shape its smoothness prefers, then each band is put on
    that curve's scale over the levels the band's own samples cover
    (:func:`mehs.synthesis.response_offset.tie_bands_to_reference`): a band's scale is
    not fixed by its data, and the gauge at ``Z_mid`` took it from the extrapolation of a
    dark band that never reaches ``Z_mid`` (its radiance −100 %… +70 % of the truth).

    A constant added to ``f`` is not fixed by the data (it cancels in
    ``f(raw) − f(dark)``, so the merge does not see it); it is set so that the curve
    follows the plain Debevec–Malik curve over the well-exposed levels
    (:func:`mehs.synthesis.response_offset.match_constant`).

    ``smoothness``: λ as given, or None (default): :data:`DEFAULT_SMOOTHNESS`, except for a
    shared curve of a bright bracket that keeps the rounds under ``offset="auto"``, whose λ
    is chosen from :data:`SMOOTHNESS_CANDIDATES` by the held-out offset misfit
    (:func:`mehs.synthesis.response_select.pick_smoothness`); the curve's ``smoothness`` is
    the λ used, its ``parameters["smoothness_choice"]`` the candidates' scores.
    ``warm_from`` (shared curves, ``offset="rounds"``): the rounds converge at that λ and
    continue :data:`SMOOTHNESS_ROUNDS` rounds at ``smoothness`` — how a chosen λ's curve is
    made, so that the check (:func:`check_recovered_response`) re-recovers it alike.
    """
    choose = smoothness is None
    smoothness = DEFAULT_SMOOTHNESS if choose else smoothness
    L = 1 << bracket.bit_depth
    P = len(bracket.exposures)
    nb = bracket.shape[2]
    sat = np.full(nb, 0.98 * (L - 1)) if saturation is None else np.broadcast_to(saturation, (nb,))
    n = samples or int(np.ceil(2.0 * L / (P - 1)))
    npix = bracket.shape[0] * bracket.shape[1] if pool is None else len(pool)
    if shared:
        n_per = _shared_per_band(n, nb)
    else:
        n_per = n
    if offset not in ("auto", "direct", "rounds"):
        raise InputError(f"unknown offset solve {offset!r}; use 'auto', 'direct' or 'rounds'")
    if offset == "rounds" and not shared:
        # the rounds a per-band curve can afford stop far from their fixed point
        # (response_solves.OFFSET_ITERATIONS_SHARED's notes): refused rather than silently biased
        raise InputError("offset='rounds' is for shared curves only; a per-band curve "
                         "takes the direct solve (offset='auto' or 'direct')", bracket.source)
    if not shared and npix < n:
        raise InputError(f"{npix} pixels are too few for a per-band "
                         f"{bracket.bit_depth}-bit curve from {P} exposures ({n} "
                         "needed); use a shared curve", bracket.source)
    cand, cdark = _candidate_levels(bracket, max(4 * n_per, 8192), seed, sat, levels != "raw",
                                    pool=pool)
    opts = {"smoothness": smoothness, "seed": seed, "levels": levels, "weighting": weighting,
            "offset": offset, "offset_iterations": offset_iterations}
    if shared:
        return _recover_from(bracket, cand, cdark, True, n_per, choose_smoothness=choose,
                             warm_from=warm_from, **opts)[0]
    # the reference (the bands' shape where their data are thin): the direct shared curve
    # (its darkest decile nearer the truth than 60 rounds', 5 exposures ×4: −4.7 vs −7.3 % per
    # band), but on a dark bracket the one auto keeps: the direct one put dark gamma brackets'
    # bands 9–22 % off the true curve's merge; now ≤ 2 %
    ref = _recover_from(bracket, cand, cdark, True, _shared_per_band(n, nb), **{
        **opts, "offset": "auto-reference" if offset == "auto" else "direct"})[0]
    curve, Z, D, f = _recover_from(bracket, cand, cdark, False, n_per, reference=ref, **opts)
    # one scale per band is not fixed by the data (E_i is per band too): the gauge
    # g(Z_mid) = ln Z_mid fixed it at a level a dark band never reaches, so its scale was
    # the smoothness prior's extrapolation (lamp scene, gamma sensor: the blue band at
    # −97 % or +63 % of the truth). Tie each band to the shared curve — the sensor's
    # common non-linearity — over the levels that band's samples cover.
    from mehs.synthesis.response_offset import tie_bands_to_reference

    # the linear-domain table before its constant was chosen (offset model), else g
    g, stats = tie_bands_to_reference(curve.table(nb) if f is None else f, ref.g, Z,
                                      None if f is None else D, weighting_table(weighting, L))
    # each band above the levels its own pairs tie: a power law, not the prior's line
    from mehs.synthesis.response_extend import covered_top, extend_power_law

    g = extend_power_law(g, covered_top(Z, weighting_table(weighting, L), per_channel=True))
    return ResponseCurve(g, curve.bit_depth, method=curve.method, smoothness=curve.smoothness,
                         weighting=curve.weighting, wavelengths=curve.wavelengths,
                         parameters={**curve.parameters, **stats})


def _shared_per_band(n: int, nb: int) -> int:
    """Samples per band of a shared curve that is to have ``n`` samples in all."""
    return max(64, int(np.ceil(n / nb)) + 1)


def _recover_from(bracket: Bracket, cand: np.ndarray, cdark: np.ndarray, shared: bool,
                  n: int, *, smoothness: float, seed: int, levels: str, weighting,
                  offset: str, offset_iterations: int | None,
                  reference: ResponseCurve | None = None, choose_smoothness: bool = False,
                  warm_from: float | None = None):
    """The curve of :func:`recover_response` from candidate levels ``cand`` and raw darks
    ``cdark`` (P, M, bands); returns ``(curve, Z, D, f)``: the samples it was solved from,
    (n, P, C) levels and their raw darks, and the linear-domain table (C, L) of the
    dark-offset model before :func:`~mehs.synthesis.response_offset.match_constant` set its
    constant (D and f None
    without that model). ``reference``: a shared curve that a per-band direct solve takes
    as its pilot and its smoothness's shape (``shape_prior`` of
    :func:`~mehs.synthesis.response_offset.solve_offset_response`). ``choose_smoothness``:
    λ is chosen as :func:`recover_response` describes (``offset="auto"``, shared);
    ``warm_from`` as there."""
    L = 1 << bracket.bit_depth
    lt = np.log(bracket.times_ms)
    params = {"levels": levels, "seed": seed, "times_ms": bracket.times_ms.tolist()}
    try:
        if shared:
            Z, idx = sample_shared(cand, n, seed, bracket.bit_depth)
        else:
            Z, idx = sample_pixels(cand, n, seed=seed, bit_depth=bracket.bit_depth,
                                   return_index=True)
        curve = plain = recover_response_Debevec1997(
            Z, lt, bit_depth=bracket.bit_depth, smoothness=smoothness,
            weighting=weighting, shared=shared, wavelengths=bracket.wavelengths,
            parameters=params)
    except InputError as exc:   # array-level checks know no file: name the bracket
        raise exc.with_path(bracket.source) from None
    has_dark = levels == "raw" and all(d is not None for d in bracket.darks)
    if not has_dark:
        return curve, Z, None, None
    # the raw dark level of every sample: (n, P, C) like Z
    D = np.take_along_axis(cdark.transpose(2, 1, 0), np.maximum(idx, 0)[:, :, None],
                           axis=1).transpose(1, 2, 0)
    wt = weighting_table(weighting, L)
    zmin = int(max(Z[wt[Z] > 0].min(), 1)) if np.any(wt[Z] > 0) else 1
    solve = (bracket, Z, D, plain, wt, zmin, smoothness)
    if offset == "direct" or not shared:
        return _offset_direct(*solve, shared=shared, reference=reference)
    if offset == "rounds":
        if warm_from is None or warm_from == smoothness:
            return _offset_rounds(*solve, weighting, params, offset_iterations)
        state: dict = {}
        _offset_rounds(*solve[:-1], warm_from, weighting, params, offset_iterations, state=state)
        return _offset_rounds(*solve, weighting, params, SMOOTHNESS_ROUNDS, state=state,
                              start=True)
    # "auto", shared: on a dark bracket the curve that fits pixels neither solve saw, else the
    # rounds (response_select: the rounds' prior suits a gamma sensor, the direct's a linear)
    from mehs.synthesis.response_select import auto_offset_solve

    state: dict = {}     # the rounds' converged effective times, where stiffer λ start

    def stiffer(lam: float):
        return _offset_rounds(*solve[:-1], lam, weighting, params, SMOOTHNESS_ROUNDS,
                              state=state, start=True)

    return auto_offset_solve(
        lambda: _offset_direct(*solve, shared=True, reference=None),
        lambda: _offset_rounds(*solve, weighting, params, offset_iterations, state=state),
        cand, cdark, idx, n, seed, bracket.times_ms, bracket.bit_depth, wt,
        bright="direct" if offset == "auto-reference" else "rounds",
        stiffer=stiffer if choose_smoothness and offset == "auto" else None,
        candidates=[v for v in SMOOTHNESS_CANDIDATES if v > smoothness])


def sample_shared(cand: np.ndarray, n_per: int, seed: int,
                  bit_depth: int) -> tuple[np.ndarray, np.ndarray]:
    """The stratified sample of a shared curve's solve (and of its held-out pixels:
    :func:`mehs.synthesis.response_select.held_out_samples`, so that both draw alike).

    The picker of :func:`~mehs.synthesis.response.sample_pixels` on ``cand`` int32
    ``(P, M, C)`` (saturated samples at ``L − 1``, ``L = 2**bit_depth``), visiting order
    permuted by ``seed``, but a channel short of ``n_per`` eligible pixels is not refused:
    its unfilled slots hold ``L − 1`` (weight 0 in every weighting), the other channels
    still determine the shared curve. Returns ``Z`` int32 ``(n_per, P, C)`` and ``idx``
    int64 ``(C, n_per)``, the pixel indices into ``cand`` (−1 where unfilled).
    """
    from mehs.synthesis._kernels import stratified_pick

    P, M, C = cand.shape
    L = 1 << bit_depth
    order = np.random.default_rng(seed).permutation(M).astype(np.int64)
    idx = stratified_pick(np.ascontiguousarray(cand), order, n_per, 64, L)   # (C, n_per)
    Z = np.take_along_axis(cand.transpose(2, 1, 0), np.maximum(idx, 0)[:, :, None], axis=1)
    Z[idx < 0] = L - 1    # unfilled slots: weight 0
    return np.ascontiguousarray(Z.transpose(1, 2, 0)), idx


def linearity_auto(bracket: Bracket, saturation: np.ndarray):
    """The linearity test of ``response="auto"`` on a small probe, repeated on a finer one
    only when its answer is not clear-cut; returns ``(probe, result)`` (the probe whose
    statistics decided, for the noise model to reuse).

    The first probe (:data:`mehs.synthesis.noise.PROBE_PIXELS`) keeps the test cheap —
    under a fifth of the merge of a 512² scene (issue 16) — and settles a linear
    sensor's bracket by a wide margin: its resolution (3 standard errors) is 0.4–0.9 %
    on the simulator's scenes against the 2 % tolerance. A result within a factor 2 of
    the tolerance (deviation or resolution above half of it) is decided again on
    :data:`~mehs.synthesis.noise.PROBE_PIXELS_FINE` pixels (resolution halved): a
    dark or widely spaced bracket is then as conclusive as it could be before, and it
    is headed for the curve recovery, which costs far more, in any case.
    """
    from mehs.synthesis.noise import (PROBE_PIXELS, PROBE_PIXELS_FINE, linearity_PTC,
                                      probe_bracket, probe_pixels)

    def test(pixels: int):
        probe = probe_bracket(bracket, saturation, max_pixels=pixels)
        return probe, linearity_PTC(probe, lambda raw, dark, j: raw - dark,
                                    bit_depth=bracket.bit_depth, key="linear")

    nl, ns, nb = bracket.shape
    # a first probe that read every pixel (a small scene, or few bands, whose probe reads
    # more pixels: noise.probe_pixels) has nothing more to read on a second one
    whole = nl * ns <= probe_pixels(PROBE_PIXELS, nb)
    try:
        probe, lin = test(PROBE_PIXELS)
    except InputError:
        if whole:
            raise
        probe, lin = None, None
    clear = (lin is not None and lin["deviation"] < LINEARITY_TOLERANCE / 2
             and lin["resolution"] < LINEARITY_TOLERANCE / 2)
    if not clear and not whole:
        probe, lin = test(PROBE_PIXELS_FINE)
        lin["probe_refined"] = True
    lin["probe_pixels"] = int(probe.raw.shape[1])
    return probe, lin


def choose_response(bracket: Bracket, response: Any, *, method: str, saturation: np.ndarray,
                    smoothness: float | None, samples: int | None, seed: int, shared: bool,
                    check: bool) -> tuple[ResponseCurve, dict[str, Any], Any]:
    """The curve :func:`mehs.synthesis.fuse.fuse_bracket` merges with (its ``response``
    argument, see there); returns ``(curve, auto_info, probe)``: ``auto_info`` the
    linearity test's and the check's figures for the summary, ``probe`` the
    photon-transfer samples of the linearity test (None if it did not run)."""
    auto_info: dict[str, Any] = {}
    probe = None
    if isinstance(response, ResponseCurve):
        return response, auto_info, probe
    if not (isinstance(response, (str, Path)) and str(response) in ("auto", "linear", "debevec")):
        return ResponseCurve.load(response), auto_info, probe
    kind = str(response)
    if kind == "linear":
        return ResponseCurve.linear(bracket.bit_depth), auto_info, probe
    curve = None
    default_probe = None      # the bracket's default probe, once read (check, noise model)
    if kind == "auto":
        try:
            probe, lin = linearity_auto(bracket, saturation)
            default_probe = None if lin.get("probe_refined") else probe
            dev = lin["deviation"]
            auto_info = {"linearity_deviation": dev, "tolerance": LINEARITY_TOLERANCE,
                         "linearity_deviation_max": lin["deviation_max"],
                         "linearity_levels": lin["levels"],
                         "linearity_resolution": lin["resolution"],
                         "linearity_probe_pixels": lin["probe_pixels"],
                         "linearity_test": "exposure ratio per signal level (p75)"}
            # a coarse test still settles a deviation beyond the tolerance by more than its
            # resolution (the deviation has its noise removed already): that sensor is not
            # linear, and the linear curve must not be the fallback for it
            inconclusive = (lin["resolution"] > LINEARITY_TOLERANCE
                            and dev <= LINEARITY_TOLERANCE + lin["resolution"])
            auto_info["linearity_conclusive"] = not inconclusive
            if dev < LINEARITY_TOLERANCE and not inconclusive:
                curve = ResponseCurve.linear(bracket.bit_depth)
        except InputError as exc:
            # too little signal to tell (no well-exposed level seen by two exposures): the
            # linear curve, flagged. It used to be taken silently (a gamma-0.8 sensor's
            # 2-exposure bracket then ran −37…+21 % across brightness deciles, unflagged).
            # A curve recovered from such data is no better vouched for: the self-check
            # compares halves of the same starved samples, and on a linear sensor's dark
            # bracket (0.02/0.16/1.28 ms, window scene) a "determined" curve ran +8…−3 %
            # while the linear curve was right.
            auto_info = {"linearity_check": f"skipped ({exc.problem})",
                         "linearity_conclusive": False, "linearity_unknown": exc.problem,
                         "assumed_linear": f"{exc.problem}; no curve is vouched for by it",
                         "check": {"determined": False, "median": None, "p95": None,
                                   "reason": "the exposures share no well-exposed signal "
                                             "level"}}
            curve = ResponseCurve.linear(bracket.bit_depth)
    if curve is None:
        skip_scipy_linalg_import()     # before the first kernel
        # the merge of a recovered curve runs the stage kernel: loaded (or compiled)
        # while the curve is recovered and checked
        warm_merge_kernel([e.data for e in bracket.exposures], bracket.times_ms,
                          method=method, darks=bracket.darks,
                          bit_depth=bracket.bit_depth, saturation=saturation, linear=False)
        try:
            curve = recover_response(bracket, smoothness=smoothness, samples=samples,
                                     seed=seed, shared=shared, levels="raw",
                                     saturation=saturation)
        except InputError as exc:
            if auto_info.get("linearity_conclusive") is not False:
                raise
            # neither a linearity test nor a curve: the linear curve, flagged below
            curve = None
            auto_info["check"] = {"determined": False, "median": None, "p95": None,
                                  "reason": f"no curve recoverable ({exc.problem})"}
        if curve is not None and (check or auto_info.get("linearity_conclusive") is False):
            if probe is None:
                from mehs.synthesis.noise import probe_bracket

                # read once: the check's consistency test, then the noise model
                probe = default_probe = probe_bracket(bracket, saturation)
            auto_info["check"] = check_recovered_response(
                bracket, curve, smoothness=curve.smoothness if smoothness is None else smoothness,
                samples=samples, seed=seed,
                shared=shared, saturation=saturation, probe=default_probe)
        if (auto_info.get("linearity_conclusive") is False
                and not auto_info["check"].get("determined", False)):
            # neither test can tell: a linear sensor is the likelier (and the
            # smoother) guess, but the scene is flagged, never silently trusted
            curve = ResponseCurve.linear(bracket.bit_depth)
            test = (auto_info["linearity_unknown"]
                    if "linearity_unknown" in auto_info else
                    "linearity test inconclusive (resolution "
                    f"{auto_info['linearity_resolution']:.1%})")
            auto_info["assumed_linear"] = f"{test} and the recovered curve undetermined"
    return curve, auto_info, probe
