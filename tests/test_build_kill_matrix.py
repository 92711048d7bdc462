"""`mehs build --workers 2` killed with SIGKILL at several points (issue 17, defects 1 and 2).

Each kill leaves no process behind (the pool workers die with their parent instead of
writing ``scenes/.tmp-*`` as orphans and holding the caller's pipe), and re-running the
build finishes a dataset byte-identical to an uninterrupted one.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mehs.dataset import manifest as mf
from mehs.dataset.build import build_dataset
from mehs.dataset.quality import QualityRules

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="reads process sessions from /proc")

# 136 lines: two chunks of the merge kernel (128 lines each), so chunking is exercised
LINES, SAMPLES = 136, 6
TIMES_MS = (0.05, 0.4, 3.2)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.synthesis.response import ResponseCurve

    root = tmp_path_factory.mktemp("kill")
    scenes = []
    for i, kind in enumerate(("colorchecker", "window", "colorchecker")):
        sim = simulate_bracket(make_scene(kind, LINES, SAMPLES, seed=i), SensorModel(seed=3),
                               TIMES_MS, seed=i)
        scenes.append(write_simulated_scene(sim, root / f"s{i}", scene_id=f"s{i}"))
    curve = ResponseCurve.linear(12).save(root / "linear.json")
    # the reference: in-process, BLAS free to use every core, the response recovered
    ref = root / "ref"
    build_dataset(scenes, ref, workers=1, seed=5, progress=False, rules=QualityRules())
    return scenes, curve, ref


def _snapshot(ds: Path) -> dict[str, bytes]:
    snap = {p.relative_to(ds).as_posix(): p.read_bytes() for p in sorted(ds.rglob("*"))
            if p.is_file() and p.name != mf.MANIFEST_NAME}
    snap[mf.MANIFEST_NAME] = json.dumps(mf.strip_volatile(mf.read_manifest(ds)),
                                        sort_keys=True).encode()
    return snap


def _session_members(sid: int) -> list[int]:
    """Pids of live (non-zombie) processes in session ``sid``."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) "
        if fields[0] != "Z" and int(fields[3]) == sid:
            out.append(int(d.name))
    return out


def _state(ds: Path) -> set[str]:
    st = set()
    if (ds / ".mehs-build.lock").exists():
        st.add("lock")
    scenes = ds / "scenes"
    if scenes.is_dir():
        for d in list(scenes.iterdir()):
            if d.name.startswith(".tmp-"):
                st.add("worker")
                if (d / "hs.hdr").exists():
                    st.add("writing")
    if (ds / mf.MANIFEST_NAME).exists():
        st.add("committed")
    return st


# lock: before any worker started; worker: workers started a scene; writing: a worker is
# writing a scene's files; committed: one scene in the manifest, others in flight;
# None: not killed — two workers must give the bytes of the in-process reference (defect 2)
KILL_POINTS = ("lock", "worker", "writing", "committed", None)


@pytest.mark.parametrize("point", KILL_POINTS)
def test_killed_build_leaves_nothing_running_and_resumes_identically(setup, tmp_path, point):
    scenes, curve, ref = setup
    ds = tmp_path / "ds"
    cmd = [sys.executable, "-m", "mehs", "build", *map(str, scenes), "--out", str(ds),
           "--workers", "2", "--seed", "5", "--quiet"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    # its own session: every process it starts (workers, resource tracker) is findable
    proc = subprocess.Popen(cmd, start_new_session=True, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    if point is None:
        out, _ = proc.communicate(timeout=300)
        assert proc.returncode == 0, out.decode(errors="replace")
        a, b = _snapshot(ref), _snapshot(ds)
        assert sorted(a) == sorted(b) and [k for k in a if a[k] != b[k]] == []
        # the resource tracker and joined workers exit right after the parent, not before:
        # on a loaded machine that can take a moment
        deadline = time.monotonic() + 5
        while _session_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _session_members(proc.pid)
        return
    while point not in _state(ds):
        assert proc.poll() is None, f"build ended before kill point {point!r}"
        assert time.monotonic() - t0 < 240, f"kill point {point!r} never reached"
        time.sleep(0.002)
    os.kill(proc.pid, signal.SIGKILL)  # the parent only, as a crash or the OOM killer would
    proc.wait()
    deadline = time.monotonic() + 5
    while _session_members(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = _session_members(proc.pid)
    if left:
        for pid in left:  # leave the machine clean even when the test fails
            os.kill(pid, signal.SIGKILL)
    assert not left, f"processes left behind after killing the build at {point!r}: {left}"
    # nobody holds the caller's pipe any more: reading it ends
    proc.stdout.read()
    proc.stdout.close()
    if point != "lock":
        m = mf.read_manifest(ds) if (ds / mf.MANIFEST_NAME).exists() else {"scenes": []}
        for e in m["scenes"]:  # whatever is listed is complete
            assert all((ds / rel).is_file() for rel in e["files"].values())
    build_dataset(scenes, ds, workers=1, seed=5, progress=False, rules=QualityRules())
    assert not [p.name for p in (ds / "scenes").iterdir() if p.name.startswith(".")]
    a, b = _snapshot(ref), _snapshot(ds)
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


# ------------------------------------------------------- determinism across workers (defect 2)

def test_scene_builds_use_one_blas_thread(setup, tmp_path, monkeypatch):
    """Why the bytes cannot depend on --workers: inside a scene build BLAS has one thread,
    whatever the process's default (the CPU count when built in-process)."""
    from threadpoolctl import threadpool_info

    import mehs.synthesis.resample as rs

    seen = []
    real = rs.apply_matrix

    def spy(*a, **k):
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
        return real(*a, **k)

    monkeypatch.setattr(rs, "apply_matrix", spy)
    scenes, curve, _ = setup
    build_dataset(scenes[:1], tmp_path / "d", workers=1, progress=False, response=curve,
                  rules=QualityRules())
    assert seen and set(seen) == {1}

