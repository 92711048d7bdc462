"""Starting and stopping `mehs sim-device` in a subprocess (shared by the capture tests)."""

from __future__ import annotations

import subprocess
import sys
import time

MEHS = [sys.executable, "-m", "mehs"]


def start_sim_device(args: list[str], *, timeout: float = 60.0):
    """``mehs sim-device ARGS`` until it prints ``ready``; returns ``(proc, {name: url})``."""
    what = " ".join(["sim-device", *[a for a in args if a.startswith("--genicam")]])
    proc = subprocess.Popen(MEHS + ["sim-device", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    urls, deadline = {}, time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"{what} exited: {proc.stderr.read()}")
        key, _, val = line.strip().partition(": ")
        if key == "ready":
            return proc, urls
        urls[key] = val
    proc.kill()
    raise AssertionError(f"{what} did not become ready")


def stop(proc) -> None:
    """Terminate, then kill after 10 s."""
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
