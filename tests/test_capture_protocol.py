"""Byte-exact protocol tests of the stage and camera drivers (PyMeasure expected_protocol style)."""

import zlib

import numpy as np
import pytest

from mehs.capture.camera import CameraError, CameraProtocolError, LineCamera, encode_line
from mehs.capture.fakeport import DISCONNECT, ExpectedPort, ProtocolMismatch
from mehs.capture.simdevice import FaultPlan, SimCamera, SimStage, SimWorld, parse_faults
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.zaber import (StageFault, StageRejected, ZaberProtocolError, ZaberStage,
                                format_command, lrc, parse_reply)
from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout, InputError


def stage_for(pairs, **kw):
    # the scripts below are written in the id-less dialect; the ids have their own tests
    port = ExpectedPort(pairs)
    kw.setdefault("message_ids", False)
    kw.setdefault("retry_delay_s", 0)
    kw.setdefault("poll_interval_s", 0)
    return ZaberStage(port, **kw), port


def cam_for(pairs, **kw):
    port = ExpectedPort(pairs)
    kw.setdefault("retry_delay_s", 0)
    return LineCamera(port, **kw), port


# ------------------------------------------------------------------ Zaber format
def test_zaber_format_and_checksum():
    assert format_command(1, 1, "move abs 1000") == b"/1 1 move abs 1000\n"
    assert format_command(1, 0, "") == b"/1 0\n"
    body = b"1 1 get pos"
    assert (sum(body) + lrc(body)) & 0xFF == 0
    assert format_command(1, 1, "get pos", checksum=True) == b"/1 1 get pos:" + f"{lrc(body):02X}".encode() + b"\n"
    r = parse_reply(b"@01 1 OK BUSY -- 0\r\n")
    assert (r.device, r.axis, r.ok, r.busy, r.flag, r.data) == (1, 1, True, True, "--", "0")
    r = parse_reply(b"@01 1 12 RJ IDLE WR BADCOMMAND")
    assert r.msg_id == 12 and not r.ok and r.flag == "WR" and r.data == "BADCOMMAND"
    with pytest.raises(ZaberProtocolError):
        parse_reply(b"@01 1 OK IDLE -- 0:00")  # wrong checksum
    with pytest.raises(ZaberProtocolError):
        parse_reply(b"@0\xff 1 OK IDLE")


def test_stage_get_position_and_warnings_bytes():
    stage, port = stage_for([
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 12800\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 02 NI WR\r\n"),
    ])
    assert stage.position() == 12800
    assert stage.warnings() == ["NI", "WR"]
    port.assert_done()


def test_stage_move_polls_until_idle_then_checks_position():
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 640\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"!01 1 IDLE --\r\n@01 1 OK IDLE -- 0\r\n"),  # an alert before the reply is skipped
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 640\r\n"),
    ])
    stage.move_abs(640)
    port.assert_done()
    assert stage.alerts == ["!01 1 IDLE --"]


def test_stage_checksums_both_ways():
    body = b"01 1 OK IDLE -- 5"
    reply = b"@" + body + b":" + f"{lrc(body):02X}".encode() + b"\r\n"
    cmd = format_command(1, 1, "get pos", checksum=True)
    stage, port = stage_for([(cmd, reply)], checksum=True)
    assert stage.position() == 5
    port.assert_done()
    stage, port = stage_for([(cmd, b"@01 1 OK IDLE -- 5\r\n")] * 4, checksum=True, retries=3)
    with pytest.raises(ZaberProtocolError, match="without checksum") as err:
        stage.position()
    assert "comm.checksum = 1" in str(err.value)        # what to change, on the device


def test_stage_rejection_is_an_error_and_again_is_retried():
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 99999999\n", b"@01 1 RJ IDLE -- BADDATA\r\n"),
    ])
    with pytest.raises(StageRejected, match="BADDATA") as ei:
        stage.move_abs(99999999)
    assert ei.value.reason == "BADDATA"
    port.assert_done()
    stage, port = stage_for([
        (b"/1 1 get pos\n", b"@01 1 RJ BUSY -- AGAIN\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 7\r\n"),
    ])
    assert stage.position() == 7
    port.assert_done()


def test_stage_garbled_query_is_retried_after_flush():
    stage, port = stage_for([
        (b"/1 1 get pos\n", b"@01 1 OK I\xffLE -- 12\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 12\r\n"),
    ])
    assert stage.position() == 12
    port.assert_done()


def test_stage_timeout_on_query_retries_then_fails_clearly():
    stage, port = stage_for([(b"/1 1 get pos\n", None)] * 3, retries=2)
    with pytest.raises(DeviceTimeout, match="after 3 attempts"):
        stage.position()
    port.assert_done()


def test_stage_lost_move_reply_is_not_blindly_repeated():
    # The move was executed but its reply was lost: the driver re-reads the state,
    # finds the stage at the target and does NOT send the move again.
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 640\n", None),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 640\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 640\r\n"),
    ])
    stage.move_abs(640)
    port.assert_done()


def test_stage_lost_move_reissued_only_when_idle_elsewhere():
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 640\n", None),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
        (b"/1 1 move abs 640\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 640\r\n"),
    ])
    stage.move_abs(640)
    port.assert_done()
    # a relative move is never re-issued
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move rel 64\n", None),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
    ])
    with pytest.raises(DeviceError, match="cannot be safely repeated"):
        stage.move_rel(64)
    port.assert_done()


def test_stage_fault_flag_stops():
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 64\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE FS 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE FS 01 FS\r\n"),
    ])
    with pytest.raises(StageFault, match="FS"):
        stage.move_abs(64)
    port.assert_done()


def test_stage_reconnects_and_rereads_state_after_disconnect():
    first = ExpectedPort([(b"/1 1 get pos\n", DISCONNECT)])
    second = ExpectedPort([
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 64\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 64\r\n"),
    ])
    ports = iter([second])
    stage = ZaberStage(first, opener=lambda: next(ports), retry_delay_s=0, message_ids=False)
    assert stage.position() == 64
    first.assert_done()
    second.assert_done()
    assert any("reconnected" in e for e in stage.events)


def test_expected_port_catches_unexpected_and_leftover():
    stage, port = stage_for([(b"/1 1 get pos\n", b"@01 1 OK IDLE -- 1\r\n@01 1 OK IDLE -- 2\r\n")])
    assert stage.position() == 1
    with pytest.raises(ProtocolMismatch, match="never read"):
        port.assert_done()
    stage, port = stage_for([(b"/1 1 home\n", b"@01 1 OK BUSY -- 0\r\n")])
    with pytest.raises(ProtocolMismatch):
        stage.position()


# ------------------------------------------------------------------ camera
def test_camera_settings_bytes():
    cam, port = cam_for([
        (b"CONF:INT 12.5\n", b"OK\n"),
        (b"CONF:INT?\n", b"12.5\n"),
        (b"SHUT CLOSE\n", b"OK\n"),
        (b"TEMP?\n", b"24.50\n"),
        (b"FORM:SHAP?\n", b"4,3\n"),
        (b"SYST:ERR?\n", b'-222,"Data out of range"\n'),
        (b"SYST:ERR?\n", b'0,"No error"\n'),
    ])
    assert cam.set_integration_time(12.5) == 12.5
    cam.set_shutter(False)
    assert cam.temperature() == 24.5
    assert cam.shape() == (4, 3)
    assert cam.errors() == ['-222,"Data out of range"']
    port.assert_done()


def test_camera_error_reply_raises_with_code():
    cam, port = cam_for([(b"CONF:INT 0.001\n", b'ERR -222,"Data out of range"\n')])
    with pytest.raises(CameraError, match="Data out of range") as ei:
        cam.set_integration_time(0.001)
    assert ei.value.code == -222
    port.assert_done()


def test_camera_block_layout_and_read_line():
    line = np.arange(12, dtype=np.uint16).reshape(4, 3) * 300
    payload = line.astype("<u2").tobytes()
    block = encode_line(line)
    assert block == (b"#224" + payload + b" " + f"{zlib.crc32(payload):08X}".encode() + b"\n")
    cam, port = cam_for([(b"FORM:SHAP?\n", b"4,3\n"), (b"READ?\n", block)])
    got = cam.read_line()
    np.testing.assert_array_equal(got, line)
    assert got.dtype == np.uint16
    port.assert_done()


IDN = (b"*IDN?\n", b"MEHS,SIMLINE-3,SIM0001,1.0\n")   # re-synchronisation before a retry


def test_camera_crc_failure_refetches_without_new_exposure():
    line = np.full((4, 3), 1000, dtype=np.uint16)
    good = encode_line(line)
    bad = bytearray(good)
    bad[10] ^= 0xFF
    cam, port = cam_for([(b"FORM:SHAP?\n", b"4,3\n"), (b"READ?\n", bytes(bad)), IDN, (b"FETC?\n", good)])
    np.testing.assert_array_equal(cam.read_line(), line)
    port.assert_done()


def test_camera_timeout_reexposes_and_persistent_fails():
    line = np.full((2, 2), 7, dtype=np.uint16)
    cam, port = cam_for([(b"FORM:SHAP?\n", b"2,2\n"), (b"READ?\n", None), IDN,
                         (b"READ?\n", encode_line(line))])
    np.testing.assert_array_equal(cam.read_line(), line)
    port.assert_done()
    cam, port = cam_for([(b"FORM:SHAP?\n", b"2,2\n")] + [(b"READ?\n", None), IDN] * 2
                        + [(b"READ?\n", None)], retries=2)
    with pytest.raises(DeviceTimeout, match="after 3 attempts"):
        cam.read_line()
    port.assert_done()


def test_camera_reconnect_reapplies_settings():
    first = ExpectedPort([(b"CONF:INT 5\n", b"OK\n"), (b"CONF:INT?\n", b"5\n"),
                          (b"SHUT OPEN\n", b"OK\n"), (b"TEMP?\n", DISCONNECT)])
    second = ExpectedPort([(b"CONF:INT 5\n", b"OK\n"), (b"SHUT OPEN\n", b"OK\n"),
                           (b"TEMP?\n", b"25.00\n")])
    ports = iter([second])
    cam = LineCamera(first, opener=lambda: next(ports), retry_delay_s=0)
    cam.set_integration_time(5)
    cam.set_shutter(True)
    assert cam.temperature() == 25.0
    first.assert_done()
    second.assert_done()


def test_camera_garbled_text_and_wrong_block_size():
    cam, port = cam_for([(b"TEMP?\n", b"2\xff.0\n"), IDN, (b"TEMP?\n", b"25.0\n")])
    assert cam.temperature() == 25.0
    port.assert_done()
    cam, port = cam_for([(b"FORM:SHAP?\n", b"4,3\n")] + [(b"READ?\n", encode_line(np.zeros((2, 2), np.uint16)))],
                        retries=0)
    with pytest.raises(CameraProtocolError, match="expected 24"):
        cam.read_line()


# ------------------------------------------------------------------ simulators speak the same bytes
@pytest.fixture()
def world():
    return SimWorld(make_scene(lines=8, samples=4), SensorModel(), pitch=64, speed=1e12)


def test_sim_stage_bytes(world):
    st = SimStage(world)
    assert st.handle(b"/1 1 get pos\n")[0] == b"@01 1 OK IDLE WR 0\r\n"
    assert st.handle(b"/1 1 move abs 64\n")[0] == b"@01 1 RJ IDLE WR BADCOMMAND\r\n"
    assert st.handle(b"/1 1 home\n")[0] in (b"@01 1 OK IDLE -- 0\r\n", b"@01 1 OK BUSY -- 0\r\n")
    st.handle(b"/1 1\n")
    assert st.handle(b"/1 1 move abs 128\n")[0] in (b"@01 1 OK BUSY -- 0\r\n", b"@01 1 OK IDLE -- 0\r\n")
    assert st.handle(b"/1 1 get pos\n")[0] == b"@01 1 OK IDLE -- 128\r\n"
    assert st.handle(b"/1 1 move abs -5\n")[0] == b"@01 1 RJ IDLE -- BADDATA\r\n"
    assert st.handle(b"/1 1 jump\n")[0] == b"@01 1 RJ IDLE -- BADCOMMAND\r\n"
    assert st.handle(b"/1 3 get pos\n")[0] == b"@01 3 RJ IDLE -- BADAXIS\r\n"
    assert st.handle(b"/2 1 get pos\n")[0] is None  # another device's address
    cmd = format_command(1, 1, "get pos", checksum=True)
    rep = st.handle(cmd)[0]
    # a device checks the command's checksum but adds one only with comm.checksum = 1
    assert rep == b"@01 1 OK IDLE -- 128\r\n"
    assert st.handle(b"/1 0 set comm.checksum 1\n")[0].rstrip()[-3:-2] == b":"
    rep = st.handle(cmd)[0]
    assert parse_reply(rep).data == "128" and rep.rstrip()[-3:-2] == b":"
    assert st.handle(cmd[:-4] + b":00\n")[0] is None  # bad checksum: ignored


def test_sim_camera_bytes(world):
    cam = SimCamera(world)
    assert cam.handle(b"CONF:INT 12.346\n")[0] == b"OK\n"
    assert cam.handle(b"CONF:INT?\n")[0] == b"12.35\n"  # 10 µs line clock
    assert cam.handle(b"CONF:INT 0\n")[0].startswith(b"ERR -222,")
    assert cam.handle(b"FETC?\n")[0].startswith(b"ERR -230,")
    assert cam.handle(b"SYST:ERR?\n")[0].startswith(b"-222,")
    assert cam.handle(b"BOGUS\n")[0].startswith(b"ERR -113,")
    assert cam.handle(b"FORM:SHAP?\n")[0] == b"4,204\n"
    block = cam.handle(b"READ?\n")[0]
    assert block.startswith(b"#41632") and len(block) == 6 + 1632 + 10
    assert cam.handle(b"FETC?\n")[0] == block


def test_fault_spec_parsing():
    fs = parse_faults("camera:garble@40, stage:disconnect@10x2")
    assert [(f.device, f.kind, f.at, f.count) for f in fs] == [("camera", "garble", 40, 1),
                                                               ("stage", "disconnect", 10, 2)]
    plan = FaultPlan(fs)
    kinds = [plan.next("stage") for _ in range(12)]
    assert kinds[9:11] == ["disconnect", "disconnect"] and kinds.count(None) == 10
    for bad in ("camera:fault@1", "lamp:timeout@1", "camera:melt@3", "camera:timeout@0"):
        with pytest.raises(InputError):
            parse_faults(bad)


def test_gige_vision_fault_spec_parsing():
    from mehs.capture.genicam_sim import GvFault, split_faults

    gv, rest = split_faults("camera:unplug@20/4ms, camera:incomplete@40x2, stage:disconnect@10,"
                            "camera:pixfmt@3/0.25ms")
    assert gv == [GvFault("unplug", 20, 1, 4000), GvFault("incomplete", 40, 2, None),
                  GvFault("pixfmt", 3, 1, 250)]
    assert rest == "stage:disconnect@10"
    for bad in ("camera:unplug@0", "camera:unplug@3/0ms", "camera:unplug@3/4", "camera:melt@3/4ms"):
        with pytest.raises(InputError, match="bad"):
            split_faults(bad)


def test_a_lost_home_is_repeated_until_the_reference_is_set():
    """A ``home`` lost on the way in leaves an unreferenced stage IDLE at 0 with ``WR``: that
    is not "homed" (it was taken for done). Home is safe to repeat, so it is sent again, and
    the stage counts as homed once ``WR`` is gone."""
    port = ExpectedPort([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 01 WR\r\n"),  # read before the first motion
        (b"/1 1 home\n", None),                                  # lost: no reply
        (b"/1 1\n", b"@01 1 OK IDLE WR 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE WR 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 01 WR\r\n"),
        (b"/1 1 home\n", b"@01 1 OK BUSY WR 0\r\n"),             # sent again
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
    ])
    stage = ZaberStage(port, retry_delay_s=0, message_ids=False)
    stage.home()
    port.assert_done()
    # a home that ends with WR still set is a fault, not success
    port = ExpectedPort([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 01 WR\r\n"),  # read before the first motion
        (b"/1 1 home\n", b"@01 1 OK BUSY WR 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE WR 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE WR 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 01 WR\r\n"),
    ])
    with pytest.raises(StageFault, match="WR"):
        ZaberStage(port, retry_delay_s=0, message_ids=False).home()
