"""`mehs sim-device` in a subprocess, for the capture benchmarks."""

from __future__ import annotations

import subprocess
import sys


def start_sim(size: int, *extra: str):
    """Start ``mehs sim-device --size SIZE EXTRA…``; returns ``(proc, {name: url})`` once ready."""
    proc = subprocess.Popen([sys.executable, "-m", "mehs", "sim-device", "--size", str(size), *extra],
                            stdout=subprocess.PIPE, text=True)
    urls = {}
    for line in proc.stdout:
        key, _, val = line.strip().partition(": ")
        if key == "ready":
            return proc, urls
        urls[key] = val
    raise SystemExit(f"{' '.join(['sim-device', *extra])} did not start")
