"""GVCP port 3956: one simulated GigE Vision camera per host, and runs that take turns for it.

Aravis's fake camera binds GVCP's fixed port on 127.0.0.1 and (Aravis 0.8.26) reports itself
running even when that bind failed; its discovery socket binds anyway. A second simulator on the
host (a second test run) then served nothing on GVCP, and its client silently drove the first
process's camera. Now simulators hold a cross-process lock while they serve and check the port.
"""

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from mehs.capture.aravis import aravis_available
from mehs.errors import DeviceError

_why = aravis_available()
pytestmark = [pytest.mark.skipif(_why is not None, reason=f"Aravis unavailable: {_why}"),
              pytest.mark.usefixtures("gvcp_port_turns")]

# One user of the simulated camera: serve it, open it over GigE Vision, read a triggered line,
# hold it a while; report which camera answered and when this process had the port.
_USER = r"""
import json, sys, time
from mehs.capture.genicam import GenicamCamera
from mehs.capture.genicam_sim import SimGenicamDevices
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel

serial = sys.argv[1]
dev = SimGenicamDevices(make_scene("ramp", lines=4, samples=8, seed=1), SensorModel(seed=1),
                        start_homed=True, serial=serial)
with dev:
    t0 = time.time()
    with GenicamCamera.open(dev.camera_url, timeout=1.0) as cam:
        ident = cam.identify()
        cam.set_integration_time(1.0)
        line = cam.read_line()
        time.sleep(1.0)
    t1 = time.time()
print(json.dumps({"serial": serial, "id": ident, "shape": list(line.shape), "t0": t0, "t1": t1}))
"""


def test_two_processes_take_turns_for_the_port():
    env = dict(os.environ)   # MEHS_GVCP_WAIT_S from the fixture: wait, do not fail
    procs = [subprocess.Popen([sys.executable, "-c", _USER, serial], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env)
             for serial in ("RUNA0001", "RUNB0002")]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-3000:]
        outs.append(json.loads(out.strip().splitlines()[-1]))
    for o in outs:   # each process drove its own camera, not the other run's
        assert o["id"].split(",")[2] == o["serial"], o
        assert o["shape"] == [8, 204]
    a, b = sorted(outs, key=lambda o: o["t0"])
    assert a["t1"] <= b["t0"], (a, b)          # served one after the other


def test_port_taken_by_another_program_is_a_clear_error():
    from mehs.capture.genicam_sim import SimGenicamDevices
    from mehs.capture.scene import make_scene

    squatter = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)   # e.g. arv-fake-gv-camera-0.8
    squatter.bind(("127.0.0.1", 3956))
    try:
        dev = SimGenicamDevices(make_scene("ramp", lines=4, samples=8, seed=1))
        t = time.monotonic()
        with pytest.raises(DeviceError, match=r"port 3956 on 127\.0\.0\.1 is already in use.*"
                                              r"arv-fake-gv-camera"):
            dev.start()
        assert time.monotonic() - t < 5
        dev.camera.close()
    finally:
        squatter.close()
    with SimGenicamDevices(make_scene("ramp", lines=4, samples=8, seed=1)) as dev:   # free again
        assert dev.camera._gv is not None


def test_a_held_port_fails_at_once_naming_the_holder(monkeypatch):
    from mehs.capture.gvcp_lock import GvcpPortLock

    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom mehs.capture.gvcp_lock import GvcpPortLock\n"
         "GvcpPortLock('127.0.0.1', 0).acquire()\nprint('held', flush=True)\ntime.sleep(60)"],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        monkeypatch.delenv("MEHS_GVCP_WAIT_S")        # a person's sim-device: no waiting
        t = time.monotonic()
        with pytest.raises(DeviceError, match=rf"process {holder.pid}\) serves 127\.0\.0\.1:3956.*"
                                              r"MEHS_GVCP_WAIT_S"):
            GvcpPortLock("127.0.0.1").acquire()
        assert time.monotonic() - t < 1
        with pytest.raises(DeviceError, match=r"waited 0\.3 s"):
            GvcpPortLock("127.0.0.1", 0.3).acquire()
    finally:
        holder.kill()
        holder.wait()
    lock = GvcpPortLock("127.0.0.1").acquire()       # the kernel freed it with the process
    with pytest.raises(DeviceError, match="already serves"):
        GvcpPortLock("127.0.0.1").acquire()           # one per process, too
    lock.release()


def test_bad_wait_setting_is_a_clear_error(monkeypatch):
    from mehs.capture.gvcp_lock import GvcpPortLock
    from mehs.errors import InputError

    monkeypatch.setenv("MEHS_GVCP_WAIT_S", "ten")
    with pytest.raises(InputError, match="MEHS_GVCP_WAIT_S='ten' is not a number"):
        GvcpPortLock("127.0.0.1")
