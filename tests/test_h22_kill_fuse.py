"""`mehs fuse` killed while it writes its folder (SIGKILL, power loss: no clean-up runs).

Deterministic versions of what tools/kill_sweep.py found: the process ends with
``os._exit`` at a chosen write, then the folder is inspected and the same command re-run.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mehs.cli import main

LINES, SAMPLES = 12, 5


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("fusekill")
    sim = simulate_bracket(make_scene("colorchecker", LINES, SAMPLES, seed=1),
                           SensorModel(seed=2), (0.1, 0.8, 6.4), seed=1)
    return write_simulated_scene(sim, root / "sc", scene_id="sc")


def _killed_fuse(args: list[str], at: str) -> None:
    """Run ``mehs fuse ARGS`` in a child that dies (``os._exit``, no clean-up) when it
    starts writing the fusion file ``at`` (``mask.png``, ``confidence.exr``)."""
    code = (
        "import os, sys\n"
        "import mehs.io.atomic as at\n"
        "real = at.atomic_path\n"
        "def dying(path, **kw):\n"
        f"    if os.path.basename(str(path)) == {at!r}:\n"
        "        os._exit(137)\n"
        "    return real(path, **kw)\n"
        "at.atomic_path = dying\n"
        "from mehs.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    r = subprocess.run([sys.executable, "-c", code, "fuse", *args], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 137, r.stderr


def _files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())
            if p.is_file() and not p.name.startswith(".") and p.name != "summary.json"}


def _summary_matches_files(out: Path) -> None:
    """A summary.json, if there, records the SHA-256 of exactly the files beside it."""
    import hashlib

    if not (out / "summary.json").exists():
        return
    rec = json.loads((out / "summary.json").read_text())["sha256"]
    have = {n: hashlib.sha256(b).hexdigest() for n, b in _files(out).items()}
    assert rec == have


def test_a_fuse_killed_while_writing_is_finished_by_the_same_command(scene, tmp_path, capsys):
    ref = tmp_path / "ref"
    assert main(["fuse", str(scene), "--out", str(ref), "--response", "linear"]) == 0
    out = tmp_path / "out"
    _killed_fuse([str(scene), "--out", str(out), "--response", "linear"], at="mask.png")
    assert (out / "radiance.hdr").exists() and not (out / "summary.json").exists()
    # the same command (no --force): the unfinished run's files are replaced, not refused
    args = ["fuse", str(scene), "--out", str(out), "--response", "linear"]
    assert main(args) == 0, capsys.readouterr().err
    assert _files(out) == _files(ref)
    _summary_matches_files(out)


def test_a_forced_refuse_killed_half_way_leaves_no_summary_of_the_earlier_run(scene, tmp_path):
    out = tmp_path / "out"
    assert main(["fuse", str(scene), "--out", str(out), "--method", "debevec",
                 "--response", "linear"]) == 0
    _summary_matches_files(out)
    before = _files(out)
    # the new run replaces radiance.hdr/.dat, then dies before the mask: the folder holds
    # the new radiance beside the earlier mask; the earlier summary must not vouch for it
    _killed_fuse([str(scene), "--out", str(out), "--force", "--response", "linear"], at="mask.png")
    assert _files(out)["radiance.dat"] != before["radiance.dat"]
    assert not (out / "summary.json").exists()
    assert main(["fuse", str(scene), "--out", str(out), "--response", "linear"]) == 0
    _summary_matches_files(out)


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
def test_write_envi_hashes_what_it_writes(tmp_path, interleave):
    """The summary's radiance digest is taken while writing: it must be the file's."""
    import hashlib

    import numpy as np

    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi

    data = np.random.default_rng(1).random((7, 5, 3)).astype(np.float64)
    got: dict[str, str] = {}
    write_envi(tmp_path / "c.hdr", SpectralCube(data, [500.0, 600.0, 700.0]), dtype="float32",
               interleave=interleave, data_ext=".dat", sha256=got)
    assert got == {n: hashlib.sha256((tmp_path / n).read_bytes()).hexdigest()
                   for n in ("c.hdr", "c.dat")}
