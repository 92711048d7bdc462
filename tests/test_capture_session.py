"""Capture sessions through the real drivers and the simulated devices (in-process, loopback TCP)."""

import json

import numpy as np
import pytest

from mehs.capture import scenefolder as sf
from mehs.capture.camera import LineCamera
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.session import Scanner, auto_exposure, capture_scene
from mehs.capture.simdevice import SimDevices
from mehs.capture.simulate import simulate_bracket
from mehs.capture.zaber import ZaberStage
from mehs.errors import DeviceError, InputError
from mehs.io.specim import read_specim_folder

LINES, SAMPLES = 12, 6
TIMES = [0.05, 0.8, 12.8]
GEOM = dict(lines=LINES, dark_lines=4, white_lines=4, progress=False)
# per exposure: 4 dark + 4 white + 12 scan = 20 line reads (camera) and 20 moves (stage, +1 home)


@pytest.fixture(scope="module")
def scene():
    return make_scene(lines=LINES, samples=SAMPLES, seed=2)


@pytest.fixture(scope="module")
def reference(scene):
    return simulate_bracket(scene, SensorModel(seed=5), TIMES, dark_lines=4)


def open_drivers(dev, timeout=0.2):
    st = ZaberStage.open(dev.stage_url, timeout=timeout, retry_delay_s=0.0, poll_interval_s=0.0)
    cam = LineCamera.open(dev.camera_url, timeout=timeout, retry_delay_s=0.0)
    return st, cam


def run_capture(scene, out, faults=None, **kw):
    with SimDevices(scene, SensorModel(seed=5), faults=faults) as dev:
        st, cam = open_drivers(dev)
        try:
            return capture_scene(st, cam, out, **{**GEOM, **kw}), dev.world.plan.fired
        finally:
            st.close()
            cam.close()


def raw_cubes(out, doc):
    return [np.asarray(read_specim_folder(out / e["folder"]).raw.data) for e in doc["exposures"]]


def test_capture_equals_simulate_bracket(scene, reference, tmp_path):
    doc, _ = run_capture(scene, tmp_path / "s", times_ms=TIMES)
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    for k, e in enumerate(doc["exposures"]):
        cap = read_specim_folder(tmp_path / "s" / e["folder"])
        np.testing.assert_array_equal(np.asarray(cap.raw.data), reference.exposures[k])
        # the shutter-closed lines as read: their mean is the simulator's, exactly
        np.testing.assert_array_equal(np.asarray(cap.darkref.data), reference.dark_frames[k])
        np.testing.assert_allclose(np.asarray(cap.darkref.data, float).mean(axis=0),
                                   reference.darks[k], rtol=1e-6)
        assert cap.raw.integration_time_ms == TIMES[k]
        assert e["requested_integration_time_ms"] == TIMES[k] and e["integration_time_ms"] == TIMES[k]
        assert e["stage"]["end_position"] == (LINES - 1) * sf.DEFAULT_PITCH
        assert sf.verify_exposure(tmp_path / "s", e) == []
        assert {"frame_rate_hz", "temperature_c", "started", "finished", "saturation_fraction"} <= set(e)
    on_disk = json.loads((tmp_path / "s" / "scene.json").read_text())
    assert on_disk["plan"]["times_ms"] == TIMES and on_disk["software_version"].startswith("mehs")


RECOVERABLE = ["camera:garble@30", "camera:timeout@30", "camera:partial@30", "camera:disconnect@30",
               "stage:timeout@30", "stage:garble@30", "stage:partial@30", "stage:disconnect@30",
               "stage:again@30x3", "camera:garble@45,stage:disconnect@50"]


@pytest.mark.parametrize("faults", RECOVERABLE)
def test_transient_faults_recover_with_identical_data(scene, reference, tmp_path, faults):
    doc, fired = run_capture(scene, tmp_path / "s", faults=faults, times_ms=TIMES)
    assert fired, "the fault was not injected"
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    for got, want in zip(raw_cubes(tmp_path / "s", doc), reference.exposures):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("faults,match", [
    ("stage:fault@30", "stage fault FS"),
    ("camera:disconnect@30x50", "connection lost"),
    ("camera:timeout@30x50", "after 4 attempts"),
])
def test_persistent_fault_stops_resumable_then_resume_completes(scene, reference, tmp_path, faults, match):
    out = tmp_path / "s"
    with pytest.raises(DeviceError, match=match) as ei:
        run_capture(scene, out, faults=faults, times_ms=TIMES)
    assert "--resume" in str(ei.value)
    doc = sf.read_scene_json(out)
    # read 30 is in exposure 1: exposure 0 complete and intact, exposure 1 incomplete
    assert [e["status"] for e in doc["exposures"]] == ["complete", "incomplete"]
    assert sf.verify_exposure(out, doc["exposures"][0]) == []
    assert "error" in doc["exposures"][1]
    assert not (out / doc["exposures"][1]["folder"]).exists()
    first = (out / doc["exposures"][0]["folder"] / "capture").stat().st_mtime_ns
    doc2, _ = run_capture(scene, out, resume=True)
    assert [e["status"] for e in doc2["exposures"]] == ["complete"] * 3
    assert (out / doc2["exposures"][0]["folder"] / "capture").stat().st_mtime_ns == first  # not redone
    for got, want in zip(raw_cubes(out, doc2), reference.exposures):
        np.testing.assert_array_equal(got, want)


def test_resume_refuses_tampered_exposure_and_overwrite(scene, tmp_path):
    out = tmp_path / "s"
    doc, _ = run_capture(scene, out, times_ms=TIMES[:2])
    with pytest.raises(InputError, match="--resume"):
        run_capture(scene, out, times_ms=TIMES[:2])
    raw = out / doc["exposures"][0]["folder"] / "capture" / (doc["exposures"][0]["folder"].split("/")[1] + ".raw")
    data = bytearray(raw.read_bytes())
    data[100] ^= 1
    raw.write_bytes(bytes(data))
    with pytest.raises(InputError, match="SHA-256"):
        run_capture(scene, out, resume=True)


def test_orphan_folder_of_unrecorded_exposure_is_moved_aside(scene, tmp_path):
    out = tmp_path / "s"
    with pytest.raises(DeviceError):
        run_capture(scene, out, faults="camera:timeout@30x50", times_ms=TIMES)
    doc = sf.read_scene_json(out)
    # simulate a kill between renaming the folder and updating scene.json
    stray = out / "exposures" / sf.exposure_folder_name(1, TIMES[1])
    stray.mkdir(parents=True)
    (stray / "partial.txt").write_text("left by a killed run")
    doc2, _ = run_capture(scene, out, resume=True)
    assert [e["status"] for e in doc2["exposures"]] == ["complete"] * 3
    aside = [p for p in (out / "exposures").iterdir() if p.name.startswith(".orphan-1_")]
    assert len(aside) == 1 and (aside[0] / "partial.txt").exists()


def test_auto_exposure_meets_its_rules(tmp_path):
    scene = make_scene(lines=24, samples=16, seed=1)
    sensor = SensorModel(seed=5)
    with SimDevices(scene, sensor, start_homed=True) as dev:
        st, cam = open_drivers(dev)
        try:
            times, info = auto_exposure(Scanner(st, cam), lines=24, probe_lines=24)
        finally:
            st.close()
            cam.close()
    assert len(times) == 3 and times[0] < times[1] < times[2]
    assert times[2] / times[0] >= 4
    np.testing.assert_allclose(times[1], np.sqrt(times[0] * times[2]), rtol=0.02)
    sim = simulate_bracket(scene, sensor, times, dark_lines=4)
    # shortest: (almost) nothing saturated
    assert np.mean(sim.exposures[0] >= 0.98 * 4095) <= 1e-4
    # ... but not needlessly short: a 2× longer exposure would saturate or the peak is well used
    assert np.quantile(sim.exposures[0], 1 - 1e-4) > 0.3 * 4095
    # longest: the darkest decile well above the dark noise
    sig = sim.exposures[2].astype(float) - sim.darks[2][None]
    assert np.quantile(sig, 0.10) >= 0.5 * info["useful_dn"]


def test_bad_requests(scene, tmp_path):
    with pytest.raises(InputError):
        run_capture(scene, tmp_path / "a", times_ms=[2.0, 1.0])
    with pytest.raises(InputError):
        run_capture(scene, tmp_path / "b", times_ms=TIMES, auto=True)
    with pytest.raises(InputError):
        run_capture(scene, tmp_path / "c", resume=True)


def test_capture_over_a_pseudo_terminal(scene, reference, tmp_path):
    pytest.importorskip("termios")
    with SimDevices(scene, SensorModel(seed=5), transport="pty", faults="camera:garble@25") as dev:
        assert dev.stage_url.startswith("/dev/")
        st, cam = open_drivers(dev, timeout=0.5)
        try:
            doc = capture_scene(st, cam, tmp_path / "s", times_ms=TIMES, **GEOM)
        finally:
            st.close()
            cam.close()
        assert dev.world.plan.fired == [("camera", 25, "garble")]
    for got, want in zip(raw_cubes(tmp_path / "s", doc), reference.exposures):
        np.testing.assert_array_equal(got, want)


def test_resume_refuses_a_different_camera(scene, tmp_path):
    out = tmp_path / "s"
    with pytest.raises(DeviceError):
        run_capture(scene, out, faults="camera:timeout@30x50", times_ms=TIMES)
    other = make_scene(lines=LINES, samples=SAMPLES + 2, seed=2)
    with pytest.raises(DeviceError, match="not the one"):
        run_capture(other, out, resume=True)
