"""Frames in flight across a switch from free-running to trigger mode (GenICam step lines after a scan).

A continuous scan free-runs; the next exposure's dark references are triggered lines. Frames the
camera sent before AcquisitionStop can still be on the link (SFNC: AcquisitionStop ends at the end
of the current frame; a switch or a busy host delays delivery) and may arrive after the first
trigger. The camera may number its frames afresh from AcquisitionStart, so their block ids do not
tell, and they arrive after the trigger: without flushing the stream on the switch, the first
triggered line was a free-running frame (here: the lit scene in a dark reference).
"""

import numpy as np
import pytest

from mehs.capture.aravis import aravis_available

_why = aravis_available()
pytestmark = [pytest.mark.skipif(_why is not None, reason=f"Aravis unavailable: {_why}"),
              pytest.mark.usefixtures("gvcp_port_turns")]

SIZE, SEED = 12, 5


def _expected(scene, line, t_ms, shutter_open):
    from mehs.capture.sensor import SensorModel, exposure_seed_for
    from mehs.capture.simulate import world_radiance_line

    return SensorModel(seed=SEED).expose_line(world_radiance_line(scene, line, 0), t_ms,
                                              exposure_seed=exposure_seed_for(t_ms), line_index=line,
                                              shutter_open=shutter_open, wavelengths=scene.wavelengths)


@pytest.mark.parametrize("delay_ms", [0, 150])
def test_frames_in_flight_at_the_switch_to_trigger_mode_are_not_a_line(delay_ms):
    from mehs.capture.genicam import GenicamCamera
    from mehs.capture.genicam_sim import SimGenicamDevices
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.zaber import ZaberStage

    scene = make_scene("colorchecker", lines=SIZE, samples=SIZE, seed=SEED)
    # every GVSP packet reaches the host 150 ms after the camera sent it (a slow link)
    dev = SimGenicamDevices(scene, SensorModel(seed=SEED), start_homed=True, link_delay_ms=delay_ms)
    with dev, ZaberStage.open(dev.stage_url) as stage, GenicamCamera.open(dev.camera_url, timeout=1.0) as cam:
        assert cam.set_integration_time(2.0) == 2.0
        stage.move_abs(4 * 64)
        with cam.stream(50.0) as s:          # free-running, shutter open, stationary on line 4
            got = []
            while len(got) < 6:
                got += s.poll(1.0)
        lit = _expected(scene, 4, 2.0, True)
        np.testing.assert_array_equal(got[-1].line, lit)
        cam.set_shutter(False)               # a dark reference, triggered
        dark = cam.read_line()
        second = cam.read_line()
    expect = _expected(scene, 4, 2.0, False)
    assert not np.array_equal(expect, lit)
    np.testing.assert_array_equal(dark, expect)
    np.testing.assert_array_equal(second, expect)
    if delay_ms:
        assert any("after AcquisitionStop" in e for e in cam.events), cam.events
