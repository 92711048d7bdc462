"""Zaber checksums end to end through the command line.

``mehs capture --checksum`` puts Zaber's ``:CC`` LRC on every command and requires one on
every reply; a stage adds them to its replies only with ``comm.checksum`` = 1. The
simulator can now start so (``mehs sim-device --comm-checksum``), and ``capture --simulate
--checksum`` sets its in-process stage so, as a user sets a real one once.
"""

import json
import subprocess

from mehs.cli import main
from _simdevice import MEHS, start_sim_device, stop

SIZE = 8
SMALL = ["--lines", str(SIZE), "--times", "1,2", "--dark-lines", "2", "--white-lines", "2",
         "--no-progress", "--timeout", "5"]


def test_capture_with_checksums_against_sim_device_comm_checksum(tmp_path):
    proc, urls = start_sim_device(["--size", str(SIZE), "--seed", "1", "--comm-checksum"])
    try:
        out = tmp_path / "scene"
        r = subprocess.run(MEHS + ["capture", "--stage", urls["stage"], "--camera", urls["camera"],
                                   "--out", str(out), "--checksum", *SMALL],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        doc = json.loads((out / "scene.json").read_text())
        assert [e["status"] for e in doc["exposures"]] == ["complete"] * 2
        # and a capture without --checksum still works: the device checks a command's
        # checksum only when one is sent, and the driver takes replies with one
        r = subprocess.run(MEHS + ["capture", "--stage", urls["stage"], "--camera", urls["camera"],
                                   "--out", str(tmp_path / "plain"), *SMALL],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
    finally:
        stop(proc)


def test_capture_with_checksums_against_a_stage_without_comm_checksum_says_what_to_do(tmp_path):
    proc, urls = start_sim_device(["--size", str(SIZE), "--seed", "1"])
    try:
        r = subprocess.run(MEHS + ["capture", "--stage", urls["stage"], "--camera", urls["camera"],
                                   "--out", str(tmp_path / "scene"), "--checksum", *SMALL],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode != 0
        assert "comm.checksum = 1" in r.stderr
    finally:
        stop(proc)


def test_capture_simulate_with_checksums(tmp_path, capsys):
    out = tmp_path / "scene"
    assert main(["capture", "--simulate", "--size", str(SIZE), "--seed", "1", "--checksum",
                 "--out", str(out), *SMALL]) == 0
    doc = json.loads((out / "scene.json").read_text())
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 2


def test_sim_device_comm_checksum_sets_the_simulated_stage():
    from mehs.cli import build_parser
    from mehs.cli.sim_device import build_devices

    args = build_parser().parse_args(["sim-device", "--size", str(SIZE), "--comm-checksum"])
    dev = build_devices(args)
    try:
        assert dev.stage.comm_checksum == 1
        assert dev.stage.handle(b"/1 0 get comm.checksum\n")[0].startswith(b"@01 0 OK IDLE WR 1:")
    finally:
        dev.close()
    dev = build_devices(build_parser().parse_args(["sim-device", "--size", str(SIZE)]))
    try:
        assert dev.stage.comm_checksum == 0       # a new stage's default
    finally:
        dev.close()
