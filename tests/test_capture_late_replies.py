"""Replies that come after the host's timeout (a slow link, a busy controller).

Zaber: each command carries a message id and only the reply echoing it is taken. Line
camera: before a retry the link is re-synchronised with ``*IDN?`` (the camera answers in
order). Either way a late reply is dropped instead of shifting every later reply by one."""

import numpy as np
import pytest

from mehs.capture.camera import LineCamera, encode_line
from mehs.capture.fakeport import ExpectedPort
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.session import capture_scene
from mehs.capture.simdevice import SimDevices
from mehs.capture.simulate import simulate_bracket
from mehs.capture.zaber import ZaberProtocolError, ZaberStage
from mehs.errors import DeviceError
from mehs.io.specim import read_specim_folder


def stage_for(pairs, **kw):
    port = ExpectedPort(pairs)
    return ZaberStage(port, retry_delay_s=0, poll_interval_s=0, **kw), port


def test_commands_carry_increasing_ids_that_wrap_at_100():
    stage, port = stage_for([
        (b"/1 1 00 get pos\n", b"@01 1 00 OK IDLE -- 12800\r\n"),
        (b"/1 1 01 warnings\n", b"@01 1 01 OK IDLE -- 00\r\n"),
    ])
    assert stage.position() == 12800 and stage.warnings() == []
    port.assert_done()
    stage, port = stage_for([
        (b"/1 1 99 get pos\n", b"@01 1 99 OK IDLE -- 5\r\n"),
        (b"/1 1 00 get pos\n", b"@01 1 00 OK IDLE -- 6\r\n"),
    ])
    stage._next_id = 99
    assert [stage.position(), stage.position()] == [5, 6]
    port.assert_done()


def test_a_late_reply_is_dropped_not_read_as_the_next_commands_answer():
    stage, port = stage_for([
        (b"/1 1 00 get pos\n", None),                       # no reply before the timeout
        # the retry: the first attempt's answer arrives first (another value: the stage moved)
        (b"/1 1 01 get pos\n", b"@01 1 00 OK IDLE -- 640\r\n@01 1 01 OK IDLE -- 700\r\n"),
        (b"/1 1 02 warnings\n", b"@01 1 02 OK IDLE -- 01 WR\r\n"),
    ])
    assert stage.position() == 700
    assert stage.warnings() == ["WR"]
    port.assert_done()
    assert any("dropped a late reply" in e and "id 00" in e for e in stage.events)


def test_without_ids_the_same_late_reply_shifts_the_answers():
    """The failure the ids prevent: the id-less dialect reads the late 640 as the retry's answer
    and the retry's answer as the warnings' (a protocol error at best, a wrong number at worst)."""
    stage, port = stage_for([
        (b"/1 1 get pos\n", None),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 640\r\n@01 1 OK IDLE -- 700\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 01 WR\r\n"),
    ], message_ids=False)
    assert stage.position() == 640             # stale
    stage.retries = 0                          # (a retry would discard the input and resync)
    with pytest.raises(ZaberProtocolError, match="counts 700 flags"):
        stage.warnings()


def test_a_device_that_does_not_echo_ids_gets_an_actionable_error():
    stage, _ = stage_for([(b"/1 1 00 get pos\n", b"@01 1 OK IDLE -- 5\r\n")], retries=0)
    with pytest.raises(ZaberProtocolError, match="message_ids=False|--no-message-ids"):
        stage.position()


# ---------------------------------------------------------------- through the simulated devices
LINES, TIMES = 12, [0.05, 0.8, 12.8]


@pytest.fixture(scope="module")
def scene():
    return make_scene(lines=LINES, samples=6, seed=2)


def _capture(scene, out, faults, message_ids=True):
    with SimDevices(scene, SensorModel(seed=5), faults=faults) as dev:
        st = ZaberStage.open(dev.stage_url, timeout=0.2, retry_delay_s=0.0, poll_interval_s=0.0,
                             message_ids=message_ids)
        cam = LineCamera.open(dev.camera_url, timeout=0.2, retry_delay_s=0.0)
        try:
            doc = capture_scene(st, cam, out, times_ms=TIMES, lines=LINES, dark_lines=4,
                                white_lines=4, progress=False)
            return doc, dev.world.plan.fired
        finally:
            st.close()
            cam.close()


@pytest.mark.parametrize("faults", ["stage:late@5", "stage:late@30x3"])
def test_late_stage_replies_recover_with_identical_data(scene, tmp_path, faults):
    ref = simulate_bracket(scene, SensorModel(seed=5), TIMES, dark_lines=4)
    doc, fired = _capture(scene, tmp_path / "s", faults, True)
    assert fired and all(k == "late" for _, _, k in fired)
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    for e, want in zip(doc["exposures"], ref.exposures):
        np.testing.assert_array_equal(np.asarray(read_specim_folder(tmp_path / "s" / e["folder"]).raw.data),
                                      want)


def test_late_stage_reply_without_ids_stops_the_capture(scene, tmp_path):
    with pytest.raises(DeviceError, match="--resume"):
        _capture(scene, tmp_path / "s", "stage:late@5", False)


def test_resume_hint_keeps_the_links_options():
    from argparse import Namespace

    from mehs.cli.capture import _resume_hint

    args = Namespace(out="scenes/s1", simulate=False, stage="/dev/ttyUSB0", camera="socket://cam:5",
                     checksum=True, no_message_ids=True)
    assert _resume_hint(args).endswith("--stage /dev/ttyUSB0 --camera socket://cam:5 "
                                       "--checksum --no-message-ids")
    args.checksum = args.no_message_ids = False
    assert _resume_hint(args).endswith("--camera socket://cam:5")


# ---------------------------------------------------------------- line camera
IDN = b"MEHS,SIMLINE-2,SIM0001,1.0\n"


def test_camera_late_line_is_dropped_by_the_resync():
    late, line = np.full((2, 2), 5, np.uint16), np.full((2, 2), 9, np.uint16)
    port = ExpectedPort([(b"FORM:SHAP?\n", b"2,2\n"), (b"READ?\n", None),
                         (b"*IDN?\n", encode_line(late) + IDN), (b"READ?\n", encode_line(line))])
    cam = LineCamera(port, retry_delay_s=0)
    np.testing.assert_array_equal(cam.read_line(), line)
    port.assert_done()
    assert any("dropped a late line" in e for e in cam.events)


def test_camera_resync_skips_the_tail_of_a_cut_reply_and_other_owed_replies():
    line = np.full((2, 2), 9, np.uint16)
    tail = encode_line(np.full((2, 2), 0x0A0A, np.uint16))[5:]      # a block cut by the discard
    port = ExpectedPort([(b"FORM:SHAP?\n", b"2,2\n"), (b"READ?\n", None),
                         (b"*IDN?\n", tail + b"OK\n" + IDN), (b"READ?\n", encode_line(line))])
    cam = LineCamera(port, retry_delay_s=0)
    np.testing.assert_array_equal(cam.read_line(), line)
    port.assert_done()


def test_camera_resync_uses_the_known_identification():
    line = np.full((2, 2), 9, np.uint16)
    other = b"ACME,OTHER,1,2\n"     # looks like an IDN but is not this camera's
    port = ExpectedPort([(b"*IDN?\n", IDN), (b"FORM:SHAP?\n", b"2,2\n"), (b"READ?\n", None),
                         (b"*IDN?\n", other + IDN), (b"READ?\n", encode_line(line))])
    cam = LineCamera(port, retry_delay_s=0)
    assert cam.identify() == IDN.decode().strip()
    np.testing.assert_array_equal(cam.read_line(), line)
    port.assert_done()


@pytest.mark.parametrize("faults", ["camera:late@12", "camera:late@30", "camera:late@30,stage:late@31"])
def test_late_camera_lines_recover_with_identical_data(scene, tmp_path, faults):
    ref = simulate_bracket(scene, SensorModel(seed=5), TIMES, dark_lines=4)
    doc, fired = _capture(scene, tmp_path / "s", faults)
    assert fired
    for e, want in zip(doc["exposures"], ref.exposures):
        np.testing.assert_array_equal(np.asarray(read_specim_folder(tmp_path / "s" / e["folder"]).raw.data),
                                      want)


def test_without_the_resync_a_late_line_shifts_the_scan(scene, tmp_path, monkeypatch):
    """What the resync prevents: each later line of the exposure read one behind, silently."""
    monkeypatch.setattr(LineCamera, "_resync", lambda self: None)
    ref = simulate_bracket(scene, SensorModel(seed=5), TIMES, dark_lines=4)
    doc, _ = _capture(scene, tmp_path / "s", "camera:late@30")
    got = [np.asarray(read_specim_folder(tmp_path / "s" / e["folder"]).raw.data) for e in doc["exposures"]]
    assert not all(np.array_equal(g, w) for g, w in zip(got, ref.exposures))
