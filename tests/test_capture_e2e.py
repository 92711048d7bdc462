"""End to end: `mehs sim-device` (a separate process) + `mehs capture` over loopback sockets."""

import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from mehs.capture import scenefolder as sf
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from _simdevice import MEHS, start_sim_device, stop

SIZE = 32
TIMES = [1.0, 4.0, 16.0]


def start_sim(*extra):
    return start_sim_device(["--size", str(SIZE), "--seed", "3", *extra])


def capture(urls, out, *extra, timeout=120):
    return subprocess.run(MEHS + ["capture", "--stage", urls["stage"], "--camera", urls["camera"],
                                  "--out", str(out), "--lines", str(SIZE), "--no-progress", *extra],
                          capture_output=True, text=True, timeout=timeout)


def read_raw(scene_dir, rec):
    import spectral.io.envi as envi

    name = rec["folder"].split("/")[-1]
    img = envi.open(str(scene_dir / rec["folder"] / "capture" / f"{name}.hdr"))
    dark = envi.open(str(scene_dir / rec["folder"] / "capture" / f"DARKREF_{name}.hdr"))
    return np.asarray(img.open_memmap()), np.asarray(dark.open_memmap())[0].astype(np.float64), img


@pytest.fixture(scope="module")
def sim():
    proc, urls = start_sim()
    yield urls
    stop(proc)


def test_sim_device_prints_urls(sim):
    assert sim["stage"].startswith("socket://127.0.0.1:") and sim["camera"].startswith("socket://")
    assert sim["lines"] == str(SIZE)


def test_capture_over_sockets_matches_sensor_model(sim, tmp_path):
    out = tmp_path / "scene"
    r = capture(sim, out, "--times", ",".join(map(str, TIMES)))
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "scene.json").read_text())
    assert doc["format"] == "mehs-scene/1"
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    scene = make_scene("colorchecker", lines=SIZE, samples=SIZE, seed=3)
    sensor = SensorModel(seed=3)
    raws, darks = [], []
    for k, rec in enumerate(doc["exposures"]):
        raw, dark, img = read_raw(out, rec)
        assert raw.shape == (SIZE, SIZE, 204) and raw.dtype == np.uint16
        assert float(img.metadata["tint"]) == TIMES[k]
        assert sf.verify_exposure(out, rec) == []
        raws.append(raw.astype(np.float64))
        darks.append(dark)
        # the recorded signal follows the sensor model at this integration time
        ok = raw < 4000
        expected = sensor.expected_dn(scene.radiance, TIMES[k])
        assert raw[ok].mean() == pytest.approx(expected[ok].mean(), rel=0.01)
    # signal ∝ integration time where no exposure saturates
    ok = np.all([r < 4000 for r in raws], axis=0) & (raws[0] - darks[0] > 20)
    rates = [((r - d)[ok] / t).mean() for r, d, t in zip(raws, darks, TIMES)]
    assert rates[1] / rates[0] == pytest.approx(1.0, rel=0.03)
    assert rates[2] / rates[0] == pytest.approx(1.0, rel=0.03)
    # dark references differ per integration time (dark current)
    dm = [d.mean() for d in darks]
    assert dm[0] < dm[1] < dm[2]
    assert dm[2] - dm[0] == pytest.approx(sensor.dark_current_e_per_ms * 15 * sensor.gain_dn_per_e, rel=0.25)


def test_killed_capture_is_resumable(tmp_path):
    """kill -9 during exposure 1 (the device hangs): exposure 0 stays complete, 1 incomplete; --resume finishes."""
    out = tmp_path / "scene"
    # exposure 0 = 16 dark + 16 white + 32 scan lines: read 70 is inside exposure 1
    proc, urls = start_sim("--faults", "camera:timeout@70x100000")
    try:
        cap = subprocess.Popen(MEHS + ["capture", "--stage", urls["stage"], "--camera", urls["camera"],
                                       "--out", str(out), "--lines", str(SIZE), "--no-progress",
                                       "--times", ",".join(map(str, TIMES)), "--timeout", "30"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        # wait for the event (exposure 1 recorded, as incomplete, before its first read), with a
        # deadline only for a capture that never gets there: a busy host may take its time
        deadline = time.monotonic() + 180
        while True:
            try:
                doc = json.loads((out / "scene.json").read_text())
                if len(doc["exposures"]) == 2:
                    break
            except (FileNotFoundError, json.JSONDecodeError):
                pass
            assert cap.poll() is None, cap.stderr.read()
            if time.monotonic() > deadline:
                cap.kill()
                cap.wait()
                pytest.fail("the capture did not start exposure 1 within 180 s")
            time.sleep(0.1)
        time.sleep(0.3)  # let it get stuck on the hung read (exposure 1 is incomplete either way)
        cap.kill()
        cap.wait()
    finally:
        stop(proc)
    doc = sf.read_scene_json(out)
    assert [e["status"] for e in doc["exposures"]] == ["complete", "incomplete"]
    assert sf.verify_exposure(out, doc["exposures"][0]) == []
    first_raw = read_raw(out, doc["exposures"][0])[0].copy()

    proc, urls = start_sim()
    try:
        r = capture(urls, out, "--resume")
        assert r.returncode == 0, r.stderr
        assert "kept" in r.stderr
    finally:
        stop(proc)
    doc = sf.read_scene_json(out)
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    np.testing.assert_array_equal(read_raw(out, doc["exposures"][0])[0], first_raw)
    sensor = SensorModel(seed=3)
    scene = make_scene("colorchecker", lines=SIZE, samples=SIZE, seed=3)
    from mehs.capture.simulate import simulate_bracket

    ref = simulate_bracket(scene, sensor, TIMES)
    for k, rec in enumerate(doc["exposures"]):
        np.testing.assert_array_equal(read_raw(out, rec)[0], ref.exposures[k])


def test_capture_errors_are_clear(tmp_path):
    r = subprocess.run(MEHS + ["capture", "--stage", "socket://127.0.0.1:1", "--camera",
                               "socket://127.0.0.1:1", "--out", str(tmp_path / "x"), "--times", "1,2"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.startswith("mehs: error: socket://127.0.0.1:1: cannot open port")


def test_capture_simulate_shortcut_writes_truth(tmp_path, capsys):
    from mehs.cli import main
    from mehs.io.envi import read_envi

    out = tmp_path / "sim"
    assert main(["capture", "--simulate", "--size", "12", "--out", str(out), "--times", "1,4,16",
                 "--dark-lines", "2", "--white-lines", "2", "--no-progress", "--seed", "4"]) == 0
    doc = sf.read_scene_json(out)
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3 and doc["seed"] == 4
    truth = read_envi(out / doc["truth"])
    np.testing.assert_array_equal(np.asarray(truth.data),
                                  make_scene("colorchecker", lines=12, samples=12, seed=4).radiance)
    assert len(doc["truth_dn_per_ms_per_radiance"]) == 204
    assert main(["capture", "--simulate", "--size", "12", "--out", str(out), "--times", "1,4"]) == 2
    assert "--resume" in capsys.readouterr().err
