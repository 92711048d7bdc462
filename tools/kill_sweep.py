"""SIGKILL every writing ``mehs`` command at seeded points of its run and check what it leaves.

For each command: an uninterrupted reference run (its duration sets the kill grid), then for
each kill point a fresh output, the command started in its own session, SIGKILL to the whole
session after the drawn delay, and an inspection that trusts nothing mehs says about itself:

* every ENVI header's data file has exactly the size its header describes;
* every EXR opens with OpenCV (``OPENCV_IO_ENABLE_OPENEXR``), every PNG with OpenCV;
* every JSON parses; every ``sha256`` map it records (``scene.json`` exposures, a dataset
  manifest's scenes, provenance) matches the files it names;
* a dataset manifest lists no scene whose files are missing; ``scene.json`` calls no exposure
  complete whose files are missing or differ;
* the raw inputs hash the same before and after;

then the same command is run again (``--resume`` for a capture that left a scene.json) and
must succeed, with outputs equal to the reference's (bytes; JSON/XML/ENVI headers with their
time stamps removed).

Commands: capture (--simulate), resume (capture --resume of a scene killed in its last
exposure), fuse, resample, rgb, build1/build2 (--workers 1/2), rebuild (--force over a
built dataset), calibrate, export, report, evaluate. With ``--race`` a second run of the
command starts into the same output halfway to the kill point; it must be refused by the
lock (or by the overwrite rule) or run alone, and the re-run must still finish the job.

Usage::

    .venv/bin/python tools/kill_sweep.py [--points 20] [--seed 0] [--only fuse,build1]
                                         [--race] [--keep] [--base DIR]

Prints one table row per command: kill points, violations, and the first few violations.
Takes about 10 minutes for every command at 20 points on 2 cores.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
MEHS = [str(Path(sys.executable).with_name("mehs"))]
ENV = dict(os.environ, OPENCV_IO_ENABLE_OPENEXR="1", MEHS_GVCP_WAIT_S="120",
           OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONHASHSEED="0")
#: build rules every tiny simulated scene passes (so the splits and evaluate have scenes)
LAX = ["--min-dr", "0", "--max-saturated", "1", "--max-ghost", "1", "--max-invalid", "1",
       "--max-response-uncertainty", "1", "--splits", "0.5,0,0.5"]
HEX64 = re.compile(r"[0-9a-f]{64}")
ENVI_BYTES = {1: 1, 2: 2, 3: 4, 4: 4, 5: 8, 6: 8, 9: 16, 12: 2, 13: 4, 14: 8, 15: 8}
#: keys whose values are wall-clock times, host facts or durations (differ between runs)
VOLATILE = re.compile(r"(^|_)(started|finished|updated|created|datetime|date|time_s|timing|"
                      r"seconds|elapsed|run|wall|host|pid|acquisition date|device_events|"
                      r"frame_rate_hz|timings|duration|temperature_c)(_|$)", re.I)


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def tree_hashes(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): sha(p) for p in sorted(root.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------ checks
def _parse_hdr(p: Path) -> dict[str, str]:
    text = p.read_text(encoding="utf-8", errors="replace")
    if not text.startswith("ENVI"):
        raise ValueError("no ENVI magic")
    out, key, buf = {}, None, ""
    for line in text.splitlines()[1:]:
        if key is not None:
            buf += " " + line
            if "}" in line:
                out[key], key = buf, None
            continue
        if "=" in line:
            k, v = line.split("=", 1)
            k, v = k.strip().lower(), v.strip()
            if v.startswith("{") and "}" not in v:
                key, buf = k, v
            else:
                out[k] = v
    if key is not None:
        raise ValueError("unterminated brace")
    return out


def check_envi(hdr: Path) -> str | None:
    try:
        h = _parse_hdr(hdr)
        n = int(h["samples"]) * int(h["lines"]) * int(h["bands"]) * ENVI_BYTES[int(h["data type"])]
        n += int(h.get("header offset", 0))
    except Exception as exc:  # noqa: BLE001 - any defect is a finding
        return f"{hdr}: unreadable header ({exc})"
    cands = [hdr.with_suffix(s) for s in (".dat", ".raw", ".img", ".bil", ".bsq", ".bip", "")]
    cands = [c for c in cands if c != hdr and c.is_file()]
    if not cands:
        return f"{hdr}: header without data file"
    if len(cands) > 1:
        return f"{hdr}: several data files {[c.name for c in cands]}"
    if cands[0].stat().st_size != n:
        return f"{hdr}: data {cands[0].name} is {cands[0].stat().st_size} B, header says {n}"
    return None


def check_image(p: Path) -> str | None:
    """Decode the whole image: PNG with OpenCV, EXR with the OpenEXR bindings."""
    try:
        if p.suffix.lower() == ".exr":
            import OpenEXR

            f = OpenEXR.InputFile(str(p))
            for ch in f.header()["channels"]:
                f.channel(ch)
            return None
        import cv2

        ok = cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is not None
    except Exception as exc:  # noqa: BLE001
        return f"{p}: not readable ({exc})"
    return None if ok else f"{p}: not readable"


def _sha_maps(doc, path=()):
    """Yield (where, {relpath: hex}) for every dict whose values are all 64-hex digests."""
    if isinstance(doc, dict):
        vals = list(doc.values())
        if vals and all(isinstance(v, str) and HEX64.fullmatch(v) for v in vals) and all(
                isinstance(k, str) and ("/" in k or "." in k) for k in doc):
            yield path, doc
        for k, v in doc.items():
            yield from _sha_maps(v, path + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _sha_maps(v, path + (i,))


def check_json(p: Path, root: Path) -> list[str]:
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except Exception as exc:  # noqa: BLE001
        return [f"{p}: not JSON ({exc})"]
    bad = []
    if isinstance(doc, dict) and doc.get("format") == "mehs-scene/1":
        for e in doc.get("exposures", []):
            if e.get("status") == "complete":
                for rel, dig in (e.get("files") or {}).items():
                    f = p.parent / rel
                    if not f.is_file() or sha(f) != dig:
                        bad.append(f"{p}: complete exposure {e.get('folder')} file {rel} "
                                   "missing or changed")
                if not e.get("files"):
                    bad.append(f"{p}: complete exposure {e.get('folder')} records no files")
        return bad
    if isinstance(doc, dict) and doc.get("format") == "mehs-dataset/1":
        for s in doc.get("scenes", []):
            for key, rel in (s.get("files") or {}).items():
                f = p.parent / rel
                if not f.is_file():
                    bad.append(f"{p}: scene {s['id']} lists missing {rel}")
            for key, dig in (s.get("sha256") or {}).items():
                rel = (s.get("files") or {}).get(key, key)
                f = p.parent / rel
                if f.is_file() and sha(f) != dig:
                    bad.append(f"{p}: scene {s['id']} sha256 of {rel} differs")
        return bad
    for where, m in _sha_maps(doc):
        for rel, dig in m.items():
            for base in (p.parent, root):
                f = base / rel
                if f.is_file():
                    if sha(f) != dig:
                        bad.append(f"{p}: {'/'.join(map(str, where))}: sha256 of {rel} differs")
                    break
    return bad


def inspect(root: Path) -> list[str]:
    """Violations in the outputs under ``root`` (hidden temporaries are allowed)."""
    bad = []
    if not root.exists():
        return bad
    for p in sorted(root.rglob("*")):
        if not p.is_file() or any(part.startswith(".") for part in p.relative_to(root).parts):
            continue
        suf = p.suffix.lower()
        if suf == ".hdr":
            r = check_envi(p)
            if r:
                bad.append(r)
        elif suf in (".exr", ".png"):
            r = check_image(p)
            if r:
                bad.append(r)
        elif suf == ".json":
            bad += check_json(p, root)
        # a data file without its header is allowed: write_envi renames the (complete) data
        # first and the header last, so no reader takes it for a cube; the re-run replaces it
    return bad


# ------------------------------------------------------------------------------ comparing
def _strip(obj):
    if isinstance(obj, dict):
        # hashes of text files that carry a time stamp, and loopback ports, differ too
        return {k: _strip(v) for k, v in obj.items() if not VOLATILE.search(str(k))
                and not str(k).endswith((".hdr", ".xml", ".html")) and k != "url"}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def normalised(p: Path) -> bytes:
    data = p.read_bytes()
    suf = p.suffix.lower()
    if suf == ".json":
        try:
            return json.dumps(_strip(json.loads(data)), sort_keys=True).encode()
        except ValueError:
            return data
    if suf == ".csv":
        import csv
        import io

        rows = list(csv.reader(io.StringIO(data.decode("utf-8", "replace"))))
        keep = [i for i, h in enumerate(rows[0] if rows else [])
                if not re.search(r"second|time|started|finished", h)]
        return "\n".join(",".join(r[i] for i in keep if i < len(r)) for r in rows).encode()
    if suf in (".hdr", ".xml", ".html", ".md", ".txt"):
        text = data.decode("utf-8", "replace")
        text = re.sub(r"\d{4}-\d\d-\d\d[T ]\d\d:\d\d:\d\d(\.\d+)?(\+00:00|Z)?", "<T>", text)
        text = re.sub(r"\d\d-\d\d-\d{4}", "<D>", text)
        text = re.sub(r"\d\d:\d\d:\d\d(\.\d+)?(\+00:00|Z)?", "<t>", text)
        text = re.sub(r"\d+(\.\d+)? ?(s|ms)\b", "<dur>", text) if suf == ".html" else text
        return text.encode()
    return data


def compare(ref: Path, got: Path, ignore=()) -> list[str]:
    def files(r):
        return {p.relative_to(r).as_posix() for p in r.rglob("*") if p.is_file()
                and not any(part.startswith(".") for part in p.relative_to(r).parts)
                and not any(re.fullmatch(i, p.relative_to(r).as_posix()) for i in ignore)}
    a, b = files(ref), files(got)
    out = [f"missing after re-run: {x}" for x in sorted(a - b)]
    out += [f"extra after re-run: {x}" for x in sorted(b - a)]
    for x in sorted(a & b):
        if normalised(ref / x) != normalised(got / x):
            out.append(f"differs from the uninterrupted run: {x}")
    return out


# ------------------------------------------------------------------------------ running
def run(argv, cwd: Path, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run(MEHS + argv, cwd=cwd, env=ENV, capture_output=True, text=True,
                          timeout=timeout)


def run_race(argv, cwd: Path, delay: float) -> list[str]:
    """Two runs of one command into one output, the first SIGKILLed after ``delay``: the
    second must either be refused by the lock or run alone; never both write."""
    first = subprocess.Popen(MEHS + argv, cwd=cwd, env=ENV, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
    time.sleep(delay / 2)
    second = subprocess.Popen(MEHS + argv, cwd=cwd, env=ENV, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        first.wait(timeout=delay / 2)
    except subprocess.TimeoutExpired:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
    _, err = second.communicate(timeout=600)
    out = []
    refusals = ("is writing this folder", "exists", "already captured")
    if second.returncode not in (0, 1) and not any(r in err for r in refusals):
        out.append(f"second run failed rc={second.returncode}: {err.strip()[-200:]}")
    return out


def run_killed(argv, cwd: Path, delay: float) -> int | None:
    proc = subprocess.Popen(MEHS + argv, cwd=cwd, env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        return proc.wait(timeout=delay)          # finished before the kill point
    except subprocess.TimeoutExpired:
        pass
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    # the session's other members (build workers) must die too; wait for them
    for _ in range(100):
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        return -999
    return None


class Cmd:
    """One writing command: ``argv(work)`` writes ``out(work)``; ``prepare(work)`` copies inputs."""

    def __init__(self, name, argv, out, *, prepare=None, rerun=None, raw=(), ignore=()):
        self.name, self.argv, self.out = name, argv, out
        self.prepare = prepare or (lambda w: None)
        self.rerun = rerun or argv
        self.raw = raw
        self.ignore = ignore


def make_inputs(base: Path) -> dict[str, Path]:
    inp = base / "inputs"
    inp.mkdir()
    sim = ["--simulate", "--size", "16", "--times", "1,4,16", "--no-progress"]
    for name, seed in (("scA", 0), ("scB", 1)):
        r = run(["capture", *sim, "--seed", str(seed), "--out", str(inp / name)], base)
        assert r.returncode == 0, r.stderr
    r = run(["capture", "--simulate", "--size", "16", "--times", "1,4", "--no-progress",
             "--scene", "sphere", "--out", str(inp / "sphere")], base)
    assert r.returncode == 0, r.stderr
    r = run(["fuse", str(inp / "scA"), "--out", str(inp / "fu")], base)
    assert r.returncode == 0, r.stderr
    r = run(["build", str(inp / "scA"), str(inp / "scB"), "--out", str(inp / "ds"), "-q",
             "--workers", "1", *LAX], base)
    assert r.returncode in (0, 1), r.stderr
    r = run(["evaluate", str(inp / "ds"), "--models", "smits", "--split", "all",
             "--out", str(inp / "ev")], base)
    if r.returncode != 0:
        r = run(["evaluate", str(inp / "ds"), "--models", "smits", "--out", str(inp / "ev")], base)
    assert r.returncode == 0, r.stderr
    # a capture killed in its last exposure, as --resume finds it: the record says
    # incomplete, the exposure's folder never appeared
    part = inp / "scPartial"
    shutil.copytree(inp / "scA", part)
    doc = json.loads((part / "scene.json").read_text())
    last = doc["exposures"][-1]
    shutil.rmtree(part / last["folder"])
    shutil.rmtree(part / "truth", ignore_errors=True)
    last.update(status="incomplete", files={}, lines_done=3)
    doc["truth"] = None
    (part / "scene.json").write_text(json.dumps(doc, indent=2))
    return {"inp": inp}


def commands(inp: Path) -> list[Cmd]:
    sc = [str(inp / "scA"), str(inp / "scB")]
    sim = ["--simulate", "--size", "16", "--times", "1,4,16", "--no-progress"]
    hs = str(inp / "fu" / "radiance.hdr")
    cert = next((inp / "sphere").rglob("source_radiance.csv"), None)

    def copy_ds(w):
        shutil.copytree(inp / "ds", w / "ds")

    def cap_rerun(w):
        return (["capture", *sim, "--out", "sc", "--resume"] if (w / "sc" / "scene.json").exists()
                else ["capture", *sim, "--out", "sc"])

    return [
        Cmd("capture", lambda w: ["capture", *sim, "--out", "sc"], "sc", rerun=cap_rerun,
            ignore=(r".*\.png",)),
        Cmd("resume", lambda w: ["capture", *sim, "--out", "sc", "--resume"], "sc",
            prepare=lambda w: shutil.copytree(inp / "scPartial", w / "sc"),
            ignore=(r".*\.png",)),
        Cmd("fuse", lambda w: ["fuse", sc[0], "--out", "out"], "out", raw=sc[:1]),
        Cmd("resample", lambda w: ["resample", hs, "out/rs.hdr"], "out"),
        Cmd("rgb", lambda w: ["rgb", hs, "--out", "out"], "out"),
        Cmd("build1", lambda w: ["build", *sc, "--out", "out", "-q", "--workers", "1", *LAX],
            "out", raw=sc),
        Cmd("rebuild", lambda w: ["build", *sc, "--out", "out", "-q", "--workers", "1",
                                  "--force", *LAX], "out", raw=sc,
            prepare=lambda w: shutil.copytree(inp / "ds", w / "out")),
        Cmd("build2", lambda w: ["build", *sc, "--out", "out", "-q", "--workers", "2", *LAX],
            "out", raw=sc),
        Cmd("calibrate", lambda w: ["calibrate", str(inp / "sphere"), "--source", str(cert),
                                    "--out", "out/cal.json"], "out", raw=[str(inp / "sphere")]),
        Cmd("export", lambda w: ["export", hs, "--out", "out", "--format", "both"], "out"),
        Cmd("report", lambda w: ["report", "ds"], "ds", prepare=copy_ds),
        Cmd("evaluate", lambda w: ["evaluate", str(inp / "ds"), "--models", "smits",
                                   "--out", "out"], "out", raw=[str(inp / "ds")]),
    ]


def sweep(cmd: Cmd, base: Path, points: int, rng: random.Random, keep: bool,
          race: bool = False) -> dict:
    tag = f"{cmd.name}-race" if race else cmd.name
    ref = base / f"{tag}-ref"
    ref.mkdir()
    cmd.prepare(ref)
    t0 = time.monotonic()
    r = run(cmd.argv(ref), ref)
    dur = time.monotonic() - t0
    if r.returncode not in (0, 1):
        return {"name": cmd.name, "error": f"reference run failed: {r.stderr[-400:]}"}
    # the grid: `points` cells over [0.05, 1.05]·duration, one seeded draw per cell
    delays = [dur * (0.05 + (i + rng.random()) / points) for i in range(points)]
    raw_before = {p: tree_hashes(Path(p)) if Path(p).is_dir() else sha(Path(p)) for p in cmd.raw}
    found = []
    killed = 0
    for i, d in enumerate(delays):
        w = base / f"{tag}-{i:02d}"
        w.mkdir()
        cmd.prepare(w)
        if race:
            issues = [f"[{d:.2f}s race] {v}" for v in run_race(cmd.argv(w), w, d)]
            rc = None
        else:
            rc = run_killed(cmd.argv(w), w, d)
            issues = [f"[{d:.2f}s] survivor processes"] if rc == -999 else []
        killed += rc is None
        issues += [f"[{d:.2f}s killed] {v}" for v in inspect(w / cmd.out)]
        done = (w / cmd.out).exists() and not compare(ref / cmd.out, w / cmd.out, cmd.ignore)
        r2 = run(cmd.rerun(w), w)
        if done and r2.returncode == 2 and "exists" in r2.stderr:
            pass    # killed after it finished writing: refusing to redo it is right
        elif r2.returncode not in (0, 1) or (r.returncode == 0 and r2.returncode != 0):
            issues.append(f"[{d:.2f}s] re-run failed rc={r2.returncode}: "
                          f"{(r2.stderr.strip().splitlines() or [''])[-1][:200]}")
        else:
            issues += [f"[{d:.2f}s re-run] {v}" for v in inspect(w / cmd.out)]
            issues += [f"[{d:.2f}s re-run] {v}" for v in compare(ref / cmd.out, w / cmd.out,
                                                                  cmd.ignore)]
        found += issues
        if not keep and not issues:
            shutil.rmtree(w)
    for p, h in raw_before.items():
        now = tree_hashes(Path(p)) if Path(p).is_dir() else sha(Path(p))
        if now != h:
            found.append(f"raw input {p} changed")
    return {"name": tag, "duration_s": round(dur, 2), "points": points, "killed": killed,
            "violations": found}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default=None, help="comma list of command names")
    ap.add_argument("--keep", action="store_true", help="keep the work folders")
    ap.add_argument("--race", action="store_true",
                    help="start a second run into the same output while the first runs, "
                         "and SIGKILL the first")
    ap.add_argument("--base", default=None)
    a = ap.parse_args(argv)
    base = Path(a.base or tempfile.mkdtemp(prefix="mehs-kill-"))
    base.mkdir(parents=True, exist_ok=True)
    inp = base / "inputs"
    if not inp.exists():
        make_inputs(base)
    rng = random.Random(a.seed)
    only = set(a.only.split(",")) if a.only else None
    rows = []
    for cmd in commands(inp):
        if only and cmd.name not in only:
            continue
        res = sweep(cmd, base, a.points, rng, a.keep, race=a.race)
        rows.append(res)
        v = res.get("violations", [])
        print(f"{res['name']:10s} {res.get('duration_s', '-')!s:>6} s  {res.get('killed', 0):3d}"
              f"/{res.get('points', 0):<3d} killed  {len(v)} violations"
              + (f"  ERROR {res['error']}" if "error" in res else ""), flush=True)
        for line in v[:12]:
            print("    " + line, flush=True)
    print(f"work folder: {base}")
    return 1 if any(r.get("violations") or r.get("error") for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
