"""Response recovery + merge accuracy against the simulator's truth, beside OpenCV, in one run.

Sensors (linear, gamma 0.8, s-curve) × brackets (3 exposures ×4, ×30, ×140 apart,
and a 7-exposure ×4 ladder) × methods:

- ``mehs auto``     — ``response="auto"`` (linearity test → linear curve, else
  Debevec–Malik with the self-consistency check), Poisson merge;
- ``mehs ladder``   — the curve recovered from the ladder bracket of the same
  sensor, reused (``--response curve.json``);
- ``OpenCV Debevec``   — ``CalibrateDebevec`` + ``MergeDebevec``;
- ``OpenCV Robertson`` — ``CalibrateRobertson`` + ``MergeRobertson``.

OpenCV's calibration and merge take 8-bit images of 3 channels: the 12-bit,
dark-subtracted data are shifted to 8 bits and processed 3 bands at a time,
which is what a user of OpenCV has to do. Scores: median / p99 relative
error after one global scale (the curves' gauge) and median SAM (°), over
pixels unsaturated in the shortest exposure, and whether mehs flagged the curve
as undetermined ("flag").

Then the dark-offset solves of :func:`mehs.synthesis.fuse_response.recover_response` side by
side — ``offset="rounds"`` (fixed-point rounds) and ``"direct"`` (one linear solve,
:mod:`mehs.synthesis.response_offset`) — for shared curves (per-band ones take the direct
solve only), on colorchecker, lamp and natural scenes and on dark brackets (light
×10⁻³): recovery time and the merged radiance's bias across brightness deciles (ptp)
against the truth, beside the true curve's.

With ``--smoothness 100,300,1000,auto`` the offset table is repeated for each λ (shared curves,
the default offset solve; ``auto``: λ chosen from the data, as when none is given), scored
against the true curve's merge — the grid the default λ
(:data:`mehs.synthesis.response.DEFAULT_SMOOTHNESS`) and its choice were measured on.

Run: ``python benchmarks/bench_response.py [--quick] [--smoothness L1,L2,...]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))


def scores(rad, truth, valid):
    rad = np.asarray(rad, dtype=np.float64)
    # OpenCV's Robertson merge writes NaN where a band had no weighted sample: a zero there
    rad = np.where(np.isfinite(rad), rad, 0.0)
    v = valid[..., None] & (truth > 0) & np.isfinite(rad) & (rad > 0)
    s = np.median(rad[v] / truth[v])
    rel = np.abs(rad / s - truth) / truth
    cos = np.einsum("ijk,ijk->ij", rad, truth) / (np.linalg.norm(rad, axis=2)
                                                  * np.linalg.norm(truth, axis=2) + 1e-300)
    sam = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return float(np.median(rel[v])), float(np.percentile(rel[v], 99)), float(np.median(sam[valid]))


def opencv(kind, bracket, nb):
    import cv2

    cal = cv2.createCalibrateDebevec() if kind == "debevec" else cv2.createCalibrateRobertson()
    merge = cv2.createMergeDebevec() if kind == "debevec" else cv2.createMergeRobertson()
    t = (bracket.times_ms / 1000.0).astype(np.float32)
    stacks = []
    for e, d in zip(bracket.exposures, bracket.darks):
        x = np.asarray(e.data, dtype=np.float32) - (0 if d is None else d[None])
        stacks.append(np.clip(np.rint(x / 16.0), 0, 255).astype(np.uint8))
    out = np.zeros(bracket.shape, np.float32)
    for b0 in range(0, nb, 3):
        idx = [min(b, nb - 1) for b in range(b0, b0 + 3)]
        imgs = [np.ascontiguousarray(s[:, :, idx]) for s in stacks]
        resp = cal.process(imgs, t)
        out[:, :, idx] = merge.process(imgs, t, resp)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller scenes, fewer bands")
    args = ap.parse_args()
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import ResponseUndeterminedWarning, fuse_bracket

    size, step = (32, 8) if args.quick else (64, 4)
    wl = SPECIM_IQ_WAVELENGTHS[::step]
    scene = make_scene("lamp", lines=size, samples=size, wavelengths=wl, seed=1)
    brackets = {"3 x4": (1.0, 4.0, 16.0), "3 x30": (0.1, 3.0, 90.0), "3 x140": (0.01, 1.4, 197.0),
                "ladder 7 x4": tuple(0.05 * 4.0 ** k for k in range(7))}
    print(os.popen("uptime").read().strip())
    print(f"lamp scene {size}×{size}×{wl.size} bands; median rel. error / p99 / SAM° vs truth")
    head = f"{'sensor':8s} {'bracket':12s} {'method':18s} {'median':>7s} {'p99':>7s} {'SAM°':>6s}  flag"
    print(head)
    print("-" * len(head))
    for resp in ("linear", "gamma", "s-curve"):
        sensor = SensorModel(response=resp, seed=2)
        sims = {k: simulate_bracket(scene, sensor, list(t), seed=3) for k, t in brackets.items()}
        brs = {k: Bracket([SpectralCube(e, wl) for e in s.exposures], list(s.darks),
                          [None] * len(s.times_ms), s.times_ms, wl, bit_depth=12)
               for k, s in sims.items()}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ResponseUndeterminedWarning)
            ladder = fuse_bracket(brs["ladder 7 x4"], response="auto", ghosts="off").response
            for name, br in brs.items():
                sim = sims[name]
                truth = sim.truth.astype(np.float64) * sim.truth_dn_per_ms
                valid = (sim.exposures[0] < 0.98 * 4095).all(axis=2)
                rows = []
                res = fuse_bracket(br, response="auto", ghosts="off")
                rows.append(("mehs auto", res.radiance.data,
                             "UNDETERMINED" if res.summary["response_undetermined"] else ""))
                if not ladder.is_linear and name != "ladder 7 x4":
                    res = fuse_bracket(br, response=ladder, ghosts="off")
                    rows.append(("mehs ladder curve", res.radiance.data, ""))
                for kind in ("debevec", "robertson"):
                    rows.append((f"OpenCV {kind}", opencv(kind, br, wl.size), ""))
                for label, rad, flag in rows:
                    m, p, a = scores(rad, truth, valid)
                    print(f"{resp:8s} {name:12s} {label:18s} {m:7.4f} {p:7.3f} {a:6.2f}  {flag}")


def _scene(kind, size, wl, scale=1.0):
    from mehs.capture.scene import make_scene

    if kind == "natural":
        from mehs.scenes.natural import make_natural_scene

        scene = make_natural_scene(size, size, wl, seed=1)
    else:
        scene = make_scene(kind, lines=size, samples=size, wavelengths=wl, seed=1)
    if scale != 1.0:     # a dark bracket: the longest exposure barely leaves the dark level
        scene.radiance = (scene.radiance * np.float32(scale)).astype(np.float32)
    return scene


def offset_solves(quick: bool) -> None:
    """Rounds vs direct solve of the dark offset: time and decile bias vs the truth.

    Per-band curves take the direct solve only (rounds are refused for them). On dark
    brackets (light ×10⁻³) the decile bias is dominated by noise in the darkest deciles:
    the true curve's own merge is the floor to compare with (column "true")."""
    import time

    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import fuse_bracket
    from mehs.synthesis.fuse_response import recover_response
    from mehs.synthesis.response import ResponseCurve

    size, step = (72, 24) if quick else (96, 4)
    wl = SPECIM_IQ_WAVELENGTHS[::step]
    print(f"\ndark offset: rounds vs direct solve; {size}×{size}×{wl.size} bands, "
          "radiance bias across brightness deciles (ptp, %) vs truth")
    print(f"{'scene':14s} {'sensor':8s} {'bracket':8s} {'curve':8s} {'true %':>6s} {'rounds s':>8s} "
          f"{'ptp %':>6s} {'direct s':>8s} {'ptp %':>6s}")
    gl = (0.04, 0.16, 0.64, 2.56, 10.24)
    cases = [("colorchecker", 1.0, "gamma", gl), ("colorchecker", 1.0, "gamma", (0.1, 0.8, 6.4)),
             ("colorchecker", 1.0, "linear", (0.1, 0.8, 6.4)),
             ("colorchecker", 1.0, "s-curve", (1.0, 4.0, 16.0)),
             ("lamp", 1.0, "s-curve", (1.0, 4.0, 16.0)), ("lamp", 1.0, "gamma", (1.0, 4.0, 16.0)),
             ("natural", 1.0, "s-curve", (1.0, 4.0, 16.0)),
             ("natural", 1.0, "gamma", (1.0, 4.0, 16.0)),
             ("natural", 1e-3, "linear", (1.0, 4.0, 16.0)),
             ("natural", 1e-3, "s-curve", (1.0, 4.0, 16.0)),
             ("natural", 1e-3, "gamma", (1.0, 4.0, 16.0)),
             ("lamp", 1e-3, "gamma", (1.0, 4.0, 16.0))]
    for kind, scale, resp, times in cases:
        sensor = SensorModel(response=resp, seed=3)
        sim = simulate_bracket(_scene(kind, size, wl, scale), sensor, list(times))
        br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                     [None] * len(times), sim.times_ms, wl, bit_depth=12)
        truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms

        def ptp(curve):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = fuse_bracket(br, response=curve, ghosts="off")
            rad = np.asarray(res.radiance.data, np.float64)
            ok = np.broadcast_to((res.mask == 0)[..., None] & (truth > 0), rad.shape)
            lr = np.log(np.maximum(rad[ok], 1e-12) / truth[ok])
            qs = np.quantile(truth[ok], np.linspace(0, 1, 11))
            dec = [np.median(lr[(truth[ok] >= a) & (truth[ok] < b)])
                   for a, b in zip(qs[:-1], qs[1:])]
            return 100 * np.ptp(np.expm1(np.array(dec) - np.median(lr)))

        z = np.arange(4096)
        true = ptp(ResponseCurve(np.log(np.maximum(sensor.inverse_response_dn(z), 1e-3)), 12,
                                 parameters={"levels": "raw"}))
        name = kind if scale == 1.0 else f"{kind} x{scale:g}"
        for shared in (True, False):
            row = []
            for offset in ("rounds", "direct") if shared else ("direct",):
                t0 = time.perf_counter()
                curve = recover_response(br, shared=shared, offset=offset)
                row += [time.perf_counter() - t0, ptp(curve)]
            row = row if shared else [float("nan")] * 2 + row
            print(f"{name:14s} {resp:8s} {len(times)} exp.   {'shared' if shared else 'per-band':8s} "
                  f"{true:6.1f} {row[0]:8.2f} {row[1]:6.1f} {row[2]:8.2f} {row[3]:6.1f}")


def smoothness_grid(quick: bool, lams: list[float]) -> None:
    """Shared curves (default offset solve) at each λ: the merged radiance against the true
    curve's merge of the same bracket — median |ratio − 1| and the ptp of its brightness-decile
    medians (samples with >= 20 DN of true signal in the longest exposure), in %."""
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import fuse_bracket
    from mehs.synthesis.fuse_response import recover_response
    from mehs.synthesis.response import ResponseCurve

    size, step = (48, 4) if quick else (64, 1)
    wl = SPECIM_IQ_WAVELENGTHS[::step]
    print(f"\nsmoothness λ: {size}×{size}×{wl.size} bands, shared curve; median |rel| % / "
          "decile ptp % against the true curve's merge")
    heads = ["λ=auto" if v is None else f"λ={v:g}" for v in lams]
    print(f"{'scene':14s} {'sensor':9s} {'bracket':12s} " + " ".join(f"{h:>12s}" for h in heads))
    gl = tuple(0.04 * 4.0 ** k for k in range(5))
    cases = [("colorchecker", 1.0, "gamma", 0.8, (1.0, 4.0, 16.0)),
             ("colorchecker", 1.0, "gamma", 0.8, gl),
             ("colorchecker", 1.0, "gamma", 0.8, (0.1, 0.8, 6.4)),
             ("colorchecker", 1.0, "s-curve", 0.8, (1.0, 4.0, 16.0)),
             ("lamp", 1.0, "gamma", 0.5, (1.0, 4.0, 16.0)),
             ("lamp", 1.0, "s-curve", 0.8, (1.0, 4.0, 16.0)),
             ("natural", 1.0, "gamma", 0.8, (1.0, 4.0, 16.0)),
             ("natural", 1.0, "s-curve", 0.8, (1.0, 4.0, 16.0)),
             ("lamp", 1.0, "gamma", 0.8, tuple(0.05 * 4.0 ** k for k in range(7))),
             ("natural", 1e-3, "gamma", 0.8, (1.0, 4.0, 16.0)),
             ("lamp", 1e-3, "gamma", 0.8, (1.0, 4.0, 16.0)),
             # an expansive sensor: black level ~5 raw levels above 0 (response_select)
             ("natural", 1.0, "gamma", 1.4, tuple(0.05 * 4.0 ** k for k in range(6)))]
    z = np.arange(4096, dtype=np.float64)
    for kind, scale, resp, gamma, times in cases:
        sensor = SensorModel(response=resp, gamma=gamma, seed=3)
        sim = simulate_bracket(_scene(kind, size, wl, scale), sensor, list(times))
        br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                     [None] * len(times), sim.times_ms, wl, bit_depth=12)
        truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms

        def merged(curve):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = fuse_bracket(br, response=curve, ghosts="off", check_response=False)
            return np.asarray(res.radiance.data, np.float64), res.mask == 0

        ref, rok = merged(ResponseCurve(np.log(np.maximum(sensor.inverse_response_dn(z), 1e-3)),
                                        12, parameters={"levels": "raw"}))
        cells = []
        for lam in lams:
            rad, ok = merged(recover_response(br, smoothness=lam, shared=True))
            use = ((ok & rok)[..., None] & (rad > 0) & (ref > 0)
                   & (truth * float(max(times)) >= 20.0))
            q = np.log(rad[use] / ref[use])
            q -= np.median(q)
            tv = truth[use]
            qs = np.quantile(tv, np.linspace(0, 1, 11))
            dec = np.expm1([np.median(q[(tv >= a) & (tv <= b)]) for a, b in zip(qs[:-1], qs[1:])])
            cells.append(f"{100 * np.median(np.abs(np.expm1(q))):5.2f} / {100 * np.ptp(dec):4.1f}")
        name = kind if scale == 1.0 else f"{kind} x{scale:g}"
        sen = resp if resp != "gamma" else f"gamma {gamma:g}"
        print(f"{name:14s} {sen:9s} {len(times)} × ×{times[1] / times[0]:<6g} " + " ".join(f"{c:>12s}" for c in cells))


if __name__ == "__main__":
    if "--smoothness" in sys.argv:
        ap = argparse.ArgumentParser()
        ap.add_argument("--quick", action="store_true")
        ap.add_argument("--smoothness", required=True,
                        help="comma-separated λ values; 'auto': chosen from the data")
        a = ap.parse_args()
        smoothness_grid(a.quick, [None if v == "auto" else float(v)
                                  for v in a.smoothness.split(",")])
    else:
        main()
        offset_solves("--quick" in sys.argv)
