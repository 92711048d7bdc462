"""Notice flags left over from before a move are not blamed on it.

Zaber's latched flags (``NI`` move interrupted, ``NC`` manual knob, ``WL`` limit sensor, the
other ``N*`` notices) stay set until ``warnings clear``. A stage that was stopped, turned by
hand or left so by another program before the session thus showed ``NI`` after the first,
perfectly good move, and the driver raised "the move was interrupted". The driver now clears
such stale notices before a motion command and logs them by name; faults are never cleared;
``WR`` is left to homing; and an interruption during the move itself still raises.
"""

import pytest

from mehs.capture.fakeport import ExpectedPort
from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simdevice import SimStage, SimWorld
from mehs.capture.simserver import DeviceServer
from mehs.capture.zaber import StageFault, StageRejected, ZaberStage


def world_for(*, homed=True, speed=1e12):
    return SimWorld(make_scene(lines=8, samples=4), SensorModel(), pitch=64, speed=speed,
                    start_homed=homed)


@pytest.fixture()
def served():
    """``(world, stage driver)`` over loopback TCP; the world is made by the test."""
    made = []

    def make(world, **kw):
        srv = DeviceServer(SimStage(world).handle, name="stage").start()
        kw.setdefault("poll_interval_s", 0)
        stage = ZaberStage.open(srv.url, timeout=2.0, **kw)
        made.append((srv, stage))
        return stage

    yield make
    for srv, stage in made:
        stage.close()
        srv.close()


@pytest.mark.parametrize("flag", ["NI", "NC", "WL"])
def test_a_stale_notice_does_not_fail_the_first_move(served, flag):
    w = world_for()
    w.flags.add(flag)                 # left by a stop, the knob or another program
    stage = served(w)
    stage.move_abs(640)
    assert w.position() == 640
    cleared = [e for e in stage.events if "cleared" in e]
    assert len(cleared) == 1 and flag in cleared[0] and "move abs 640" in cleared[0]
    assert flag not in w.flags
    stage.move_abs(1280)             # nothing left to clear: no further event
    assert len([e for e in stage.events if "cleared" in e]) == 1


def test_stale_notices_are_cleared_before_homing_but_wr_is_left_to_it(served):
    w = world_for(homed=False)
    w.flags.update({"NI", "NC"})      # WR outranks them in the flag field
    stage = served(w)
    assert stage.warnings() == ["NC", "NI", "WR"]
    stage.home()
    assert stage.warnings() == [] and stage.home_position == 0
    assert any("NC NI" in e and "cleared" in e for e in stage.events)


def test_an_unhomed_stage_still_refuses_moves_after_the_clear(served):
    w = world_for(homed=False)
    w.flags.add("NI")
    stage = served(w)
    with pytest.raises(StageRejected, match="BADCOMMAND"):
        stage.move_abs(64)
    assert stage.warnings() == ["WR"]                 # warnings clear never clears WR
    assert not stage.is_homed()


def test_an_interruption_during_this_move_still_raises(served):
    w = world_for(speed=1.0)          # 640 s for the move: it is still running when stopped
    w.flags.add("NI")                 # and a stale one from before
    stage = served(w)
    stage.move_abs(640, wait=False)
    assert any("NI" in e and "cleared" in e for e in stage.events)
    stage.stop()
    with pytest.raises(StageFault, match=r"interrupted \(NI\)"):
        stage.wait_idle(target=640)


def test_a_fault_is_not_cleared_and_no_move_is_sent(served):
    w = world_for()
    w.flags.update({"FS", "NI"})
    stage = served(w)
    with pytest.raises(StageFault, match="FS") as ei:
        stage.move_abs(640)
    msg = str(ei.value)
    assert "warnings clear" in msg and "move abs 640" in msg     # what to do, and what was refused
    assert {"FS", "NI"} <= w.flags and w.position() == 0 and not w._moves


def test_the_clear_costs_no_round_trip_when_the_last_reply_shows_no_flag():
    """Bytes: a fresh driver reads ``warnings`` before its first motion; a stale notice is
    cleared with ``warnings clear``; the next move, after a poll that showed ``--``, goes
    straight out (a step scan pays nothing)."""
    port = ExpectedPort([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE NI 02 NI NU\r\n"),
        (b"/1 1 warnings clear\n", b"@01 1 OK IDLE NI 02 NI NU\r\n"),
        (b"/1 1 move abs 64\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 64\r\n"),
        (b"/1 1 move abs 128\n", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE -- 128\r\n"),
    ])
    stage = ZaberStage(port, message_ids=False, retry_delay_s=0, poll_interval_s=0)
    stage.move_abs(64)
    stage.move_abs(128)
    port.assert_done()
    assert stage.events == ["stage: cleared stale flags NI NU before 'move abs 64' (set before "
                            "this move: an earlier stop, the manual knob or another program; "
                            "Zaber 'warnings clear')"]


def test_live_warnings_alone_are_not_cleared():
    # WT (controller hot) follows a condition: clearing it would hide nothing and fix nothing
    port = ExpectedPort([
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WT 01 WT\r\n"),
        (b"/1 1 move abs 64\n", b"@01 1 OK BUSY WT 0\r\n"),
        (b"/1 1\n", b"@01 1 OK IDLE WT 0\r\n"),
        (b"/1 1 warnings\n", b"@01 1 OK IDLE WT 01 WT\r\n"),
        (b"/1 1 get pos\n", b"@01 1 OK IDLE WT 64\r\n"),
    ])
    stage = ZaberStage(port, message_ids=False, retry_delay_s=0, poll_interval_s=0)
    stage.move_abs(64)
    port.assert_done()
    assert not any("cleared" in e for e in stage.events)
