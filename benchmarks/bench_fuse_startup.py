"""Wall time of `mehs fuse` on one 512×512×204×3 scene, as a user runs it (issue 16).

    python benchmarks/bench_fuse_startup.py [--quick] [--size S] [--repeat N] [--skip-cold]

Rows, each a fresh ``python -m mehs`` process (median of ``--repeat``):

- ``python -c "import numpy"`` — the interpreter's own start-up (reference);
- ``mehs fuse`` with warm caches (the usual case): the merge kernel's machine code in
  the mehs cache (``MEHS_CACHE_DIR``, here a folder of the benchmark's own, filled by
  a first run), loaded without starting numba (:mod:`mehs.synthesis._native`), and
  Python's bytecode of mehs (written by that run, as in a user's shell, even where
  ``PYTHONDONTWRITEBYTECODE`` is set);
- ``mehs fuse`` with empty caches (``MEHS_CACHE_DIR`` and ``NUMBA_CACHE_DIR`` pointing
  at new folders: a first-ever run, which compiles the kernel), once (not with
  ``--skip-cold``), and how long the child process compiling the photon-transfer
  passes ran on after the command returned (the command used numpy's passes);
- the in-process stages of one warm run, as ``mehs fuse`` runs them: imports,
  loading the bracket (which starts the SHA-256 check of its files in a
  background thread), ``fuse_bracket`` — its response (linearity check), noise,
  merge (whose first kernel call loads the stored kernel) and ghost stages from
  ``summary["timings"]``, and the wait for the SHA-256 check at its end — and
  ``write_fusion``;
- the linearity check against the merge, each alone in one warm process (median of
  ``--repeat`` alternating runs): the probe (lines read for the photon-transfer
  statistics), the statistics themselves (:func:`mehs.synthesis.noise.linearity_PTC`:
  two compiled passes per exposure pair, the pairs on threads; the noise model reuses
  them) and the default merge (:func:`mehs.synthesis.merge.merge_bracket`); and the
  noise model (:func:`mehs.synthesis.noise.estimate_noise_PTC`) after the check, as
  ``mehs fuse`` runs it, and alone on a fresh probe: their difference is what the check
  adds to a fusion that measures its noise model. Inside
  ``mehs fuse`` both share the CPUs with the SHA-256 check, so only this comparison
  says what each costs.

Targets: warm ≤ 1.2 s, first-ever ≤ 6 s; the linearity check ≤ 20 % of the merge. The
load is printed before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def wall(cmd: list[str], env: dict) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    dt = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{r.stderr[-2000:]}")
    return dt


def wait_for_children(cache: Path) -> float:
    """Seconds until no process holds a ``<entry>.building`` lock in ``cache`` (a child
    compiling an entry point, :func:`mehs.synthesis._native.build_in_background`)."""
    from mehs.synthesis._native_child import locked_elsewhere

    t0 = time.perf_counter()
    while any(locked_elsewhere(m) for m in (cache / "kernels").glob("*.building")):
        time.sleep(0.05)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 128×128 scene")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--skip-cold", action="store_true",
                    help="no first-ever run (its compilation takes tens of seconds)")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_fuse_"))
    try:                   # (a 512² scene and its fusions: ~0.7 GB, removed even on failure)
        return _bench(args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _bench(args, tmp: Path) -> int:
    from _load import load_line
    from bench_build import make_scene

    size = args.size or (128 if args.quick else 512)
    scene = make_scene(tmp / "scene", size)
    env = dict(os.environ, PYTHONPATH=str(HERE.parent), MEHS_CACHE_DIR=str(tmp / "mehs_cache"))
    # Python's bytecode cache is one of the caches a warm run has: a user's shell writes
    # it, and a shell that forbids it (PYTHONDONTWRITEBYTECODE, set on the project's
    # machine) had every "warm" run compile ~60 mehs modules from source again (0.09 s)
    no_pyc = env.pop("PYTHONDONTWRITEBYTECODE", None)
    py = sys.executable
    print("before:", load_line(), flush=True)
    if no_pyc:
        print("(PYTHONDONTWRITEBYTECODE dropped for the runs below: their bytecode is cached "
              "as in a user's shell)")

    def fuse(out: str, e=env) -> float:
        shutil.rmtree(tmp / out, ignore_errors=True)
        return wall([py, "-m", "mehs", "fuse", str(scene), "--out", str(tmp / out)], e)

    fuse("warmup")                                   # fills the caches
    t_py = statistics.median(wall([py, "-c", "import numpy"], env) for _ in range(args.repeat))
    t_warm = statistics.median(fuse(f"w{i}") for i in range(args.repeat))
    cold_env = dict(env, NUMBA_CACHE_DIR=str(tmp / "numba_cache_empty"),
                    MEHS_CACHE_DIR=str(tmp / "mehs_cache_empty"))
    t_cold = float("nan") if args.skip_cold else fuse("cold", cold_env)
    # the photon-transfer passes' child compile may outlive the command (it used numpy's
    # passes meanwhile): wait for it, so that it neither loads the rows below nor goes
    # unreported
    t_child = float("nan") if args.skip_cold else wait_for_children(tmp / "mehs_cache_empty")
    # in-process breakdown of one warm run
    code = (
        "import json, time, sys; t0 = time.perf_counter()\n"
        "from mehs.cli import reuse_heap, small_pages\n"
        "small_pages(); reuse_heap()                        # as the command runs\n"
        "from mehs.synthesis.bracket import load_bracket\n"
        "from mehs.synthesis.fuse import fuse_bracket, write_fusion\n"
        "t1 = time.perf_counter()\n"
        "br = load_bracket(sys.argv[1], defer_verify=True)   # as `mehs fuse` does\n"
        "t2 = time.perf_counter()\n"
        "wait = []\n"
        "check = br.check_files\n"
        "def timed_check():\n"
        "    t = time.perf_counter(); check(); wait.append(time.perf_counter() - t)\n"
        "br.check_files = timed_check\n"
        "res = fuse_bracket(br)\n"
        "t3 = time.perf_counter(); write_fusion(res, sys.argv[2])\n"
        "t4 = time.perf_counter()\n"
        "print(json.dumps({'imports': t1 - t0, 'load': t2 - t1, 'fuse': t3 - t2,\n"
        "                  'write': t4 - t3, 'wait': sum(wait), **res.summary['timings']}))\n")
    shutil.rmtree(tmp / "bd", ignore_errors=True)
    r = subprocess.run([py, "-c", code, str(scene), str(tmp / "bd")], capture_output=True,
                       text=True, env=env)
    nan = float("nan")
    st = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else {}
    if r.returncode:
        print(f"in-process breakdown failed:\n{r.stderr[-2000:]}", file=sys.stderr)
    print(f"`mehs fuse` of one {size}×{size}×204×3 scene (median of {args.repeat})")
    print(f"{'what':<58} {'seconds':>8} {'× python+numpy':>15}")
    for label, sec in (("python -c 'import numpy' (reference)", t_py),
                       ("mehs fuse, warm caches", t_warm),
                       ("mehs fuse, first-ever run (empty caches)", t_cold),
                       ("  its child compile, still running after it returned", t_child),
                       ("  in process: imports (mehs, numpy)", st.get("imports", nan)),
                       ("  in process: load bracket (starts the SHA-256 check)",
                        st.get("load", nan)),
                       ("  in process: fuse_bracket", st.get("fuse", nan)),
                       ("    response (probe + linearity check)", st.get("response_s", nan)),
                       ("    noise model", st.get("noise_s", nan)),
                       ("    merge (+ loading the stored kernel)", st.get("merge_s", nan)),
                       ("    ghosts", st.get("ghosts_s", nan)),
                       ("    waiting for the SHA-256 check", st.get("wait", nan)),
                       ("  in process: write_fusion", st.get("write", nan))):
        print(f"{label:<58} {sec:8.2f} {sec / t_py:14.1f}×")
    # the linearity check and the merge, each alone (no SHA-256 thread beside them)
    code = (
        "import json, statistics, sys, time, numpy as np\n"
        "from mehs.cli import reuse_heap, small_pages\n"
        "small_pages(); reuse_heap()\n"
        "from mehs.synthesis.bracket import load_bracket\n"
        "from mehs.synthesis.merge import merge_bracket\n"
        "from mehs.synthesis.noise import estimate_noise_PTC, linearity_PTC, probe_bracket\n"
        "br = load_bracket(sys.argv[1], verify='none')\n"
        "sat = np.full(br.shape[2], 0.98 * (2 ** br.bit_depth - 1), np.float32)\n"
        "lin = lambda raw, dark, j: raw - dark\n"
        "def merge():\n"
        "    merge_bracket([e.data for e in br.exposures], br.times_ms, darks=br.darks,\n"
        "                  bit_depth=br.bit_depth, saturation=sat)\n"
        "merge(); linearity_PTC(probe_bracket(br, sat), lin, key='linear')   # warm\n"
        "noise = lambda p: estimate_noise_PTC(p, lin, key='linear')\n"
        "tp, ts, tm, ta, tn = [], [], [], [], []\n"
        f"for _ in range({args.repeat}):\n"
        "    t0 = time.perf_counter(); probe = probe_bracket(br, sat)\n"
        "    t1 = time.perf_counter(); linearity_PTC(probe, lin, key='linear')\n"
        "    t2 = time.perf_counter(); noise(probe)   # after the check, as mehs fuse\n"
        "    t3 = time.perf_counter(); merge(); t4 = time.perf_counter()\n"
        "    fresh = probe_bracket(br, sat)\n"
        "    t5 = time.perf_counter(); noise(fresh); t6 = time.perf_counter()\n"
        "    tp.append(t1 - t0); ts.append(t2 - t1); ta.append(t3 - t2); tm.append(t4 - t3)\n"
        "    tn.append(t6 - t5)\n"
        "m = statistics.median\n"
        "print(json.dumps({'probe': m(tp), 'stats': m(ts), 'merge': m(tm),\n"
        "                  'noise_after': m(ta), 'noise_alone': m(tn)}))\n")
    r = subprocess.run([py, "-c", code, str(scene)], capture_output=True, text=True, env=env)
    if r.returncode:
        print(f"linearity check vs merge failed:\n{r.stderr[-2000:]}", file=sys.stderr)
    else:
        lc = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"linearity check vs merge, each alone (median of {args.repeat})")
        print(f"{'what':<58} {'seconds':>8} {'× merge':>15}")
        # what the check adds to a fusion that measures its noise model (below the
        # timing's resolution, a difference of medians, shown as 0)
        own = lc["stats"] + lc["noise_after"] - lc["noise_alone"]
        for label, sec in (("  merge (default: Poisson, ghost statistic) [reference]", lc["merge"]),
                           ("  linearity check: photon-transfer statistics", lc["stats"]),
                           ("  probe: lines read for them (shared with the noise model)",
                            lc["probe"]),
                           ("  linearity check with its probe", lc["stats"] + lc["probe"]),
                           ("  noise model alone (its own photon-transfer statistics)",
                            lc["noise_alone"]),
                           ("  noise model after the check (the statistics shared)",
                            lc["noise_after"]),
                           ("  the check's cost in mehs fuse (+ noise − noise alone)",
                            own if abs(own) >= 5e-4 else 0.0)):
            print(f"{label:<58} {sec:8.3f} {sec / lc['merge']:14.2f}×")
        print("  (the target is the check with its probe; mehs fuse measures the noise model "
              "anyway, from the same probe and statistics)")
    print("targets (issue 16, 512²): warm ≤ 1.2 s; first-ever ≤ 6 s; "
          "linearity check ≤ 0.20× the merge")
    print("after: ", load_line())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
