"""Zaber driver and simulated stage against Zaber's published ASCII protocol.

Truths used: Zaber's ASCII Protocol Manual (as quoted by public drivers): a device puts a
checksum on its replies only with ``comm.checksum`` = 1; ``home`` resets the position to
``limit.home.preset`` and clears ``WR`` once the home sensor is reached (``/home`` →
``@01 0 OK BUSY WR 0``); the flag field shows only the highest-priority warning;
long replies end in ``\\`` and go on in ``#… cont …`` packets. Zaber Motion Library's
``WarningFlags`` gives the flag names and their priority; zproto's LRC test vector
``"01 tools echo"`` → ``0x8F``.
"""

import pytest

from mehs.capture.fakeport import ExpectedPort
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simdevice import SimStage, SimWorld
from mehs.capture.simserver import DeviceServer
from mehs.capture.zaber import StageFault, ZaberProtocolError, ZaberStage, lrc, parse_reply


def stage_for(pairs, **kw):
    port = ExpectedPort(pairs)
    kw.setdefault("message_ids", False)
    kw.setdefault("retry_delay_s", 0)
    kw.setdefault("poll_interval_s", 0)
    kw.setdefault("retries", 0)
    return ZaberStage(port, **kw), port


def cc(packet: bytes) -> bytes:
    """``packet`` (marker + body, no terminator) with its LRC and CR LF appended."""
    return packet + b":" + f"{lrc(packet[1:]):02X}".encode() + b"\r\n"


def test_lrc_matches_an_independent_test_vector():
    assert lrc(b"01 tools echo") == 0x8F           # zproto's checksum test


def test_one_digit_message_id_is_read():
    # Zaber's parsers (zaber.serial, zproto) read the id as any number of digits
    assert parse_reply(b"@01 1 5 OK IDLE -- 42\r\n").msg_id == 5
    stage, port = stage_for([(b"/1 1 05 get pos\n", b"@01 1 5 OK IDLE -- 42\r\n")],
                            message_ids=True)
    stage._next_id = 5
    assert stage.position() == 42
    port.assert_done()


def test_a_continued_reply_is_joined():
    stage, port = stage_for([(b"/1 1 warnings\n",
                              b"@01 1 OK IDLE FS 04 FS WL\\\r\n#01 1 cont WR\\\r\n"
                              b"!01 1 IDLE FS\r\n#01 1 cont NI\r\n")])
    assert stage.warnings() == ["FS", "WL", "WR", "NI"]
    assert stage.alerts == ["!01 1 IDLE FS"]
    port.assert_done()
    # with message ids and checksums, each packet carries its own checksum
    stage, port = stage_for([(cc(b"/1 1 00 warnings")[:-2] + b"\n",
                              cc(b"@01 1 00 OK IDLE -- 03 WT\\") + cc(b"#01 1 00 cont WV NU"))],
                            message_ids=True, checksum=True)
    assert stage.warnings() == ["WT", "WV", "NU"]
    port.assert_done()
    stage, port = stage_for([(b"/1 1 warnings\n",
                              b"@01 1 OK IDLE -- 02 WT\\\r\n#01 1 cont NU:00\r\n")])
    with pytest.raises(ZaberProtocolError, match="checksum mismatch"):
        stage.warnings()


def test_home_ends_wherever_limit_home_preset_puts_it():
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WR 01 WR\r\n"),  # read before the first motion
        (b"/1 1 home\n", b"@01 1 OK BUSY WR 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 1000\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),
    ])
    stage.home()
    assert stage.home_position == 1000
    port.assert_done()


def test_a_masked_interruption_after_a_move_is_found():
    # WT (controller hot) outranks NI in the flag field: only `warnings` shows the NI
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move rel 64\n", b"@01 1 OK BUSY WT 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE WT 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WT 02 WT NI\r\n"),
    ])
    with pytest.raises(StageFault, match="interrupted"):
        stage.move_rel(64)
    port.assert_done()
    # an informational warning alone does not stop the move; it is logged once
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 64\n", b"@01 1 OK BUSY WT 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE WT 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WT 01 WT\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE WT 64\r\n"),
    ])
    stage.move_abs(64)
    port.assert_done()
    assert any("WT" in e for e in stage.events)


@pytest.mark.parametrize("flag, meaning", [("WL", "limit sensor"), ("NC", "manual knob")])
def test_limit_and_knob_flags_stop_a_move(flag, meaning):
    stage, port = stage_for([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE -- 00\r\n"),  # read before the first motion
        (b"/1 1 move abs 640\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", f"@01 1 OK IDLE {flag} 0\r\n".encode()),
        (b"/1 1 warnings\n", f"@01 1 OK IDLE {flag} 01 {flag}\r\n".encode()),
    ])
    with pytest.raises(StageFault, match=meaning):
        stage.move_abs(640)
    port.assert_done()


# ------------------------------------------------------------------ the simulated stage
@pytest.fixture()
def world():
    return SimWorld(make_scene(lines=8, samples=4), SensorModel(), pitch=64, speed=1e12)


def test_sim_adds_reply_checksums_only_with_comm_checksum(world):
    st = SimStage(world)
    assert st.handle(b"/1 0 get comm.checksum\n")[0] == b"@01 0 OK IDLE WR 0\r\n"
    assert st.handle(cc(b"/1 1 get pos")[:-2] + b"\n")[0] == b"@01 1 OK IDLE WR 0\r\n"
    assert st.handle(b"/1 1 set comm.checksum 1\n")[0] == b"@01 1 RJ IDLE WR DEVICEONLY\r\n"
    assert st.handle(b"/1 0 set comm.checksum 2\n")[0] == b"@01 0 RJ IDLE WR BADDATA\r\n"
    st.handle(b"/1 0 set comm.checksum 1\n")
    assert st.handle(b"/1 1 get pos\n")[0] == cc(b"@01 1 OK IDLE WR 0")


def test_sim_takes_commands_without_device_and_axis(world):
    # "/set comm.checksum 1", as the driver's error message says, goes to all devices
    st = SimStage(world)
    r = parse_reply(st.handle(b"/set comm.checksum 1\n")[0])
    assert (r.device, r.axis, r.ok) == (1, 0, True) and st.comm_checksum == 1
    assert st.handle(b"/1hi\n")[0] == cc(b"@01 0 RJ IDLE WR BADCOMMAND")


def test_sim_flag_field_follows_the_priority_order(world):
    st = SimStage(world)
    world.flags.add("NI")                       # unhomed and interrupted: WR outranks NI
    assert parse_reply(st.handle(b"/1 1\n")[0]).flag == "WR"
    world.flags.add("FS")
    assert parse_reply(st.handle(b"/1 1\n")[0]).flag == "FS"
    from mehs.capture.zaber import WARNING_FLAGS

    assert WARNING_FLAGS.index("WR") < WARNING_FLAGS.index("NI")


def test_sim_home_clears_wr_only_at_the_home_sensor():
    w = SimWorld(make_scene(lines=8, samples=4), SensorModel(), pitch=64, speed=1.0)
    w.pos = 5000.0
    st = SimStage(w)
    assert st.handle(b"/1 1 home\n")[0] == b"@01 1 OK BUSY WR 0\r\n"   # the manual's example
    st.handle(b"/1 1 stop\n")
    assert st.handle(b"/1 1 warnings\n")[0] == b"@01 1 OK IDLE WR 02 NI WR\r\n"


def test_driver_checksums_against_the_simulator_over_tcp(world):
    world.homed = True
    st = SimStage(world)
    srv = DeviceServer(st.handle, name="stage").start()
    # no reply is expected to time out here, and with retries=0 a reply a busy host delayed
    # past the timeout would be a DeviceTimeout, not the checksum error: a generous timeout
    stage = ZaberStage.open(srv.url, timeout=10.0, checksum=True, retries=0)
    try:
        with pytest.raises(ZaberProtocolError, match="comm.checksum = 1"):
            stage.position()
        st.comm_checksum = 1                    # what '/1 0 set comm.checksum 1' sets
        assert stage.position() == 0
    finally:
        stage.close()
        srv.close()
