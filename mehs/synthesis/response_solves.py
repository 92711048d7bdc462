"""The two dark-offset solves of a Debevec–Malik curve on raw levels, for
:func:`mehs.synthesis.fuse_response.recover_response` (split from it for size): the direct
linear solve (:mod:`mehs.synthesis.response_offset`) and the fixed-point rounds, whose
continuation at a stiffer λ is how a λ chosen from the data is reached
(:func:`mehs.synthesis.response_select.pick_smoothness`).
"""

from __future__ import annotations

import numpy as np

from mehs.errors import InputError
from mehs.synthesis.response import recover_response_Debevec1997
from mehs.synthesis.response_extend import covered_top
from mehs.synthesis.response_offset import match_constant as _match_constant

#: Rounds of the black-level offset iterations of :func:`recover_response`. The fixed point
#: is right but reached sublinearly: on a gamma-0.8 sensor (5 exposures ×4) the radiance
#: error across brightness deciles spanned 13 % after 12 plain rounds, 3.6 % after 60
#: over-relaxed ones (1.7 % after 300 plain). A shared curve's round costs ~7 ms; a
#: per-band curve's ~200× that, so per-band curves take the direct solve only: after the
#: 12 rounds they could afford their radiance ran −15…+2 % of the truth across brightness
#: deciles (gamma sensor, 5 exposures ×4), −38…+8 % on a linear sensor, and the darkest
#: decile of a natural scene (s-curve, 3 × ×4) +67 % (the true curve −14 %, direct −18 %).
OFFSET_ITERATIONS_SHARED = 60
#: over-relaxation of those rounds: ×1.5 halves the rounds needed and stays stable (×3 diverged)
OFFSET_RELAXATION = 1.5


def _offset_direct(bracket, Z, D, plain, wt, zmin, smoothness, *, shared, reference):
    """The dark-offset model by one linear solve (``offset="direct"``); returns
    ``(curve, Z, D, f)`` as :func:`_recover_from`."""
    from mehs.synthesis.response_offset import solve_offset_response

    L = 1 << bracket.bit_depth
    try:
        # per band, the plain curve of a dark band is its prior's extrapolation: the
        # shared curve is the better pilot, and the shape its data are too few to set
        # (a dark band's prior towards a straight line put its darkest levels 30 % high)
        pilot = (reference.table() if reference is not None
                 else plain.table(None if plain.shared else Z.shape[2]))
        f, stats = solve_offset_response(Z, D, bracket.times_ms, wt, pilot,
                                         smoothness=smoothness, shared=shared,
                                         shape_prior=reference is not None)
    except InputError as exc:
        raise exc.with_path(bracket.source) from None
    # f is 1 a quarter of the range above the dark: scaled to DN-like values, as the
    # floors of _match_constant expect
    f = f * (L // 2)
    return _match_constant(f, plain, zmin, {**plain.parameters, **stats, "offset": "direct"},
                           zmax=covered_top(Z, wt)), Z, D, f


def _offset_rounds(bracket, Z, D, plain, wt, zmin, smoothness, weighting, params,
                   offset_iterations, *, state: dict | None = None, start: bool = False):
    """The dark-offset model by fixed-point rounds (``offset="rounds"``, shared curves);
    returns ``(curve, Z, D, f)`` as :func:`_recover_from`.

    ``state``: where the last round's curve and effective log times are left (keys
    ``"curve"``, ``"lt"``); with ``start`` the rounds continue from them (at this
    ``smoothness``) instead of from the plain curve and the true times."""
    L = 1 << bracket.bit_depth
    curve = plain
    if offset_iterations is None:
        offset_iterations = OFFSET_ITERATIONS_SHARED
    if offset_iterations <= 0:
        return curve, Z, None, None
    w = wt[Z]
    t = bracket.times_ms[None, :, None]
    lev = np.arange(L)
    lt_cur = np.broadcast_to(np.log(t), Z.shape)
    if start and state:
        curve, lt_cur = state["curve"], state["lt"]
    for _ in range(int(offset_iterations)):     # shared curves only (recover_response)
        G = curve.table()[0]
        B, gz = np.interp(D, lev, np.exp(G)), G[Z]
        W = w.sum(axis=1)
        lnE = np.where(W > 0, (w * (gz - lt_cur)).sum(axis=1) / np.where(W > 0, W, 1), 0.0)
        # over-relaxed (OFFSET_RELAXATION): the plain step converges sublinearly
        lt_cur = lt_cur + OFFSET_RELAXATION * (np.log(t + B / np.exp(lnE)[:, None, :]) - lt_cur)
        curve = recover_response_Debevec1997(
            Z, lt_cur, bit_depth=bracket.bit_depth, smoothness=smoothness,
            weighting=weighting, shared=True, wavelengths=bracket.wavelengths,
            parameters={**params, "offset_iterations": int(offset_iterations)})
    if state is not None and not start:
        state.update(curve=curve, lt=lt_cur)
    f = np.exp(curve.table())
    out = _match_constant(f, plain, zmin, {**curve.parameters, "offset": "rounds"},
                          zmax=covered_top(Z, wt))
    out.smoothness = float(smoothness)    # the rounds' λ (plain's is the default's)
    return out, Z, D, f
