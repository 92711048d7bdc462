"""Scale of a full dataset build: the paper's ME HS size (96 scenes × 512²×204×3), extrapolated.

    python benchmarks/bench_scale.py [--quick] [--scenes N] [--size S]

Builds the same ``--scenes`` (≥ 8) simulated scenes three ways, each in a fresh
child process (so its peak-memory figures are its own):

- 1 worker, in process;
- 2 local worker processes (``build_dataset(workers=2)``);
- a Dask ``LocalCluster`` of 2 single-threaded worker processes
  (``build_dataset(scheduler=client)``).

and prints seconds per scene, the build's wall time extrapolated to 96 scenes,
and the peak resident memory per worker (``ru_maxrss`` of the process that ran
the scenes: this process for 1 worker, the largest child for the others). The
scenes are made once, before any timing (simulator, ``window`` scene, 3
exposures). Each child runs as the ``mehs build`` command does (numpy's huge-page
advice off, in its workers too: :func:`mehs.cli.small_pages`). Reference in the same run: 1 worker, which the ratios divide.
``--quick``: 8 scenes of 128×128 (extrapolated by pixel count as well).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

PAPER_SCENES, PAPER_SIZE = 96, 512


def child(mode: str, scenes: list[str], out: str) -> None:
    from mehs.cli import small_pages

    small_pages()          # as the `mehs build` command runs (its workers inherit it)
    from mehs.dataset.build import build_dataset

    t0 = time.perf_counter()
    if mode == "dask":
        from dask.distributed import Client, LocalCluster

        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            t0 = time.perf_counter()   # the cluster's start-up is not the build's
            man = build_dataset(scenes, out, workers=2, scheduler=client, progress=False)
            wall = time.perf_counter() - t0
    else:
        man = build_dataset(scenes, out, workers=1 if mode == "1" else 2, progress=False)
        wall = time.perf_counter() - t0
    n_ok = sum(1 for e in man["scenes"] if e.get("status") in ("pass", "warn", "fail"))
    print(json.dumps({
        "wall": wall, "built": n_ok,
        "self_peak": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "children_peak": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="8 scenes of 128×128")
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--size", type=int, default=None, help="lines = samples (default 512)")
    ap.add_argument("--keep", default=None, help="folder to keep (and reuse) the simulated scenes")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help=argparse.SUPPRESS)
    ap.add_argument("scene", nargs="*", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.scene, args.out)
        return 0
    if args.scenes < 8:
        ap.error("extrapolating needs at least 8 real scenes")
    from _load import load_line
    from bench_build import make_scene

    size = args.size or (128 if args.quick else PAPER_SIZE)
    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_scale_"))
    root = Path(args.keep) if args.keep else tmp / "scenes"
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scenes = []
    for i in range(args.scenes):
        folder = root / f"scene{i:03d}_{size}"
        if not (folder / "scene.json").exists():
            make_scene(folder, size, seed=i + 1)
        scenes.append(str(folder))
    print(f"{args.scenes} scenes of {size}×{size}×204×3 ready in {time.perf_counter() - t0:.0f} s")
    env = dict(os.environ, PYTHONPATH=str(HERE.parent))
    res = {}
    for mode, label in (("1", "1 worker (in process)"), ("2", "2 local worker processes"),
                        ("dask", "Dask LocalCluster, 2 workers × 1 thread")):
        print(f"{label}: {load_line()}", flush=True)
        out = tmp / f"ds_{mode}"
        r = subprocess.run([sys.executable, __file__, "--child", mode, "--out", str(out),
                            *scenes], capture_output=True, text=True, env=env)
        if r.returncode:
            print(f"  failed:\n{r.stderr[-3000:]}")
            continue
        res[mode] = (label, json.loads(r.stdout.strip().splitlines()[-1]))
        shutil.rmtree(out, ignore_errors=True)
    scale = (PAPER_SIZE / size) ** 2
    print(f"\n{'configuration':<42} {'s/scene':>8} {'× 1 worker':>10} {'96 scenes':>10} "
          f"{'peak RSS/worker':>16}")
    ref = None
    for mode, (label, r) in res.items():
        per = r["wall"] / max(1, r["built"])
        ref = ref or per
        peak = r["self_peak"] if mode == "1" else r["children_peak"]
        est = per * scale * PAPER_SCENES
        print(f"{label:<42} {per:8.2f} {ref / per:9.2f}× {est / 60:8.1f} min "
              f"{peak / 2**20:12.0f} MiB")
    if scale != 1:
        print(f"(96 scenes extrapolated from {size}² to 512² by pixel count, ×{scale:.0f})")
    print("after:", load_line())
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
