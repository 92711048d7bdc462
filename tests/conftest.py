"""Suite-wide settings."""

import os
from pathlib import Path

import pytest

# The tiling probes of mehs's networks are cached per user (mehs.ssr.probe_cache);
# tests measure afresh unless a test points MEHS_CACHE_DIR at its own folder.
os.environ["MEHS_CACHE_DIR"] = ""


# ---------------------------------------------------------------- GigE Vision (GenICam) tests
@pytest.fixture
def gvcp_port_turns(monkeypatch):
    """Simulated GigE Vision cameras wait their turn for GVCP port 3956 (one per host).

    Another test run on the same machine (CI beside a developer, helpers in parallel)
    may be serving its simulated camera: wait for it instead of failing
    (:class:`mehs.capture.gvcp_lock.GvcpPortLock`; ``mehs sim-device`` children
    inherit the setting).
    """
    monkeypatch.setenv("MEHS_GVCP_WAIT_S", "900")


@pytest.fixture(scope="session")
def serial_scene_factory(tmp_path_factory):
    """``make(size, seed, times)``: a scene captured through the serial camera path (in-process
    simulator), made once per session for each set of arguments: the reference the GigE Vision
    captures are compared with, byte for byte."""
    made = {}

    def make(size: int, seed: int, times) -> Path:
        key = (int(size), int(seed), tuple(float(t) for t in times))
        if key not in made:
            from mehs.cli import main

            out = tmp_path_factory.mktemp("serial") / "scene"
            assert main(["capture", "--simulate", "--size", str(size), "--seed", str(seed),
                         "--out", str(out), "--times", ",".join(map(str, times)),
                         "--no-progress"]) == 0
            made[key] = out
        return made[key]

    return make
