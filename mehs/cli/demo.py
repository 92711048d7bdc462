"""`mehs demo` — the whole pipeline on the simulated device: capture, build, train, evaluate, report, export."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("--out", "-o", default="mehs-demo", metavar="DIR",
                        help="demo folder (default: %(default)s); re-running reuses its captures "
                             "and built scenes")
    parser.add_argument("--scenes", type=int, default=6, metavar="N",
                        help="scenes to capture (default: %(default)s): natural scenes from measured "
                             "spectra — a visible high-pressure sodium lamp, a moving cloud, "
                             "then daylight, window, tungsten, fluorescent, …")
    parser.add_argument("--size", default="small", metavar="small|full|N",
                        help="small = 64×64 pixels, full = 512×512 (Specim IQ), or N×N pixels; "
                             "always 204 bands (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of scenes, sensor noise, sampling and splits (default: 0)")
    parser.add_argument("--workers", "-j", type=int, default=None, metavar="N",
                        help="scenes built at once (default: CPU count)")
    parser.add_argument("--force", action="store_true",
                        help="delete this demo folder's earlier captures and outputs and start over")
    parser.add_argument("--known-response", action="store_true",
                        help="give the builder the simulated sensor's known linear curve instead "
                             "of the curve fused from a captured response ladder (no ladder is "
                             "captured)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args):
    from mehs.demo import format_summary, run_demo

    doc = run_demo(args.out, scenes=args.scenes, size=args.size, seed=args.seed,
                   workers=args.workers, force=args.force,
                   known_response=args.known_response,
                   progress=False if args.no_progress else None)
    print(format_summary(doc))
    return 0
