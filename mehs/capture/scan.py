"""Constant-velocity (continuous) pushbroom scans: the stage moves, the camera free-runs.

The stage speed comes from the frame rate × line pitch (slowed by
``oversample`` so that timing jitter yields a spare frame rather than a gap);
every frame carries a host time of mid-exposure; the stage position is read
continuously while it moves and each frame's position is interpolated from
those reads. Frame ``f`` lies at fractional scan line
``u_f = (x(t_f) − start) / pitch``; line ``k`` takes the frame nearest its
centre among those with ``round(u_f) = k``. Frames that lose that contest are
reported as duplicates; a line no frame reached is **missing**: the exposure
stops with a :class:`~mehs.errors.DeviceError` naming the lines (it is never
filled in), and ``--resume`` scans it again.

Both camera paths scan this way: a GenICam camera free-runs
(:meth:`~mehs.capture.genicam.GenicamCamera.stream`); the serial line camera
is read back to back (``READ?``), each line timestamped at the middle of its
request.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from mehs.capture.zaber import speed_setting
from mehs.errors import DeviceError, DeviceTimeout

#: The stage covers one line pitch in ``oversample`` frame periods.
DEFAULT_OVERSAMPLE = 2
#: Longest along-track travel during one exposure, in lines (motion blur).
MAX_BLUR_LINES = 0.1
#: Lines of run-up before the first and after the last scan line (acceleration, settling).
RUN_UP_LINES = 4
#: Longest wait (s) after the stage stopped for frames exposed during the scan to arrive
LATE_FRAMES_S = 2.0
#: Longest wait (s) for a free-running camera's first frame after AcquisitionStart (at
#: least 20 frame periods): cameras settle their sensor first, and a loaded host adds its
#: own stalls; a pass that gets none is scanned again (:func:`scan_continuous`).
FIRST_FRAME_S = 5.0


def assign_frames(u: np.ndarray, lines: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Pick one frame per scan line from fractional line positions.

    Parameters
    ----------
    u
        ``(frames,)`` fractional scan line of each frame (NaN = unknown position).
    lines
        Number of scan lines.

    Returns
    -------
    chosen
        ``(lines,)`` frame index per line, −1 where no frame reached the line.
    duplicates
        Frames inside the scan that another frame beat to their line.
    offset
        ``(lines,)`` ``|u − k|`` of the chosen frames (NaN where missing).
    """
    u = np.asarray(u, dtype=np.float64)
    k = np.rint(u)
    ok = np.isfinite(u) & (k >= 0) & (k < lines)
    chosen = np.full(lines, -1, dtype=np.int64)
    offset = np.full(lines, np.nan)
    idx = np.flatnonzero(ok)
    d = np.abs(u[idx] - k[idx])
    order = idx[np.lexsort((d, k[idx]))]       # by line, then by distance to the centre
    kk = k[order].astype(np.int64)
    first = np.ones(kk.size, dtype=bool)
    first[1:] = kk[1:] != kk[:-1]
    chosen[kk[first]] = order[first]
    offset[kk[first]] = np.abs(u[order[first]] - kk[first])
    return chosen, int(idx.size - np.count_nonzero(first)), offset


def _ranges(idx: np.ndarray) -> str:
    out, idx = [], list(map(int, idx))
    while idx:
        a = b = idx.pop(0)
        while idx and idx[0] == b + 1:
            b = idx.pop(0)
        out.append(f"{a}" if a == b else f"{a}–{b}")
    return ", ".join(out[:8]) + (" …" if len(out) > 8 else "")


class _SerialStream:
    """Back-to-back ``READ?`` of the serial line camera, each timestamped at mid-request."""

    def __init__(self, camera):
        self.cam, self._frames, self.rate = camera, [], None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def poll(self, timeout_s: float = 0.0) -> list:
        from mehs.capture.genicam import Frame

        t0 = time.time()
        line = self.cam.read_line()
        f = Frame(line, (t0 + time.time()) / 2.0, len(self._frames))
        self._frames.append(f)
        return [f]

    def frames(self) -> list:
        return list(self._frames)


def _line_rate(camera, t_ms: float) -> float:
    """Frames per second the camera can deliver at ``t_ms``."""
    if hasattr(camera, "stream"):
        cap = camera.max_frame_rate()
        return float(min(cap, 1000.0 / (t_ms * 1.05 + 0.05)))
    # serial camera: measure three back-to-back reads (stationary, before the run-up);
    # a line cannot come faster than its exposure (the simulator's may, unless realtime)
    t0 = time.perf_counter()
    for _ in range(3):
        camera.read_line()
    return min(3.0 / (time.perf_counter() - t0), 1000.0 / t_ms)


def _wait_for_phase(stage, frames: list, rate: float, lead_s: float) -> None:
    """Sleep until the move command puts line centres on the camera's frame clock.

    The stage reaches line 0's centre ``lead_s`` after it starts; frames expose
    (mid-exposure) at ``t_last + n / rate``. The command latency is taken as half
    a position query's round trip. Only the quality (frames on line centres)
    depends on this: positions are measured, never assumed.
    """
    if not frames:
        return
    rtt = []
    for _ in range(3):
        a = time.time()
        stage.position()
        rtt.append(time.time() - a)
    latency = float(np.median(rtt)) / 2.0
    period = 1.0 / rate
    base = frames[-1].t - lead_s - latency        # a command time that is in phase
    now = time.time() + 0.002
    t_cmd = base + np.ceil((now - base) / period) * period
    time.sleep(max(0.0, t_cmd - time.time()))


def _stage_speed(stage) -> int | None:
    try:
        return int(stage.query("get maxspeed").data)
    except (DeviceError, ValueError, AttributeError):
        return None


def scan_continuous(stage, camera, *, attempts: int = 3, **kwargs) -> tuple[np.ndarray, dict[str, Any]]:
    """A constant-velocity scan (:func:`scan_once`), scanned again while lines are missing
    or the camera did not start streaming (a new AcquisitionStart each pass).

    Each attempt is a complete new scan; missing lines are never patched from
    another pass. ``info["attempts"]`` lists why earlier passes were rejected.
    """
    failures: list[str] = []
    for attempt in range(max(1, int(attempts))):
        try:
            raw, info = scan_once(stage, camera, **kwargs)
        except (MissingLines, NoFirstFrame) as exc:
            failures.append(exc.problem)
            events = getattr(camera, "events", None)
            if events is not None:
                events.append(f"scan: pass {attempt + 1} rejected: {exc.problem}")
            if attempt + 1 >= max(1, int(attempts)):
                raise type(exc)(f"{exc.problem} (in each of {attempt + 1} passes)", exc.path) from None
            continue
        info["rejected_passes"] = failures
        return raw, info
    raise AssertionError("unreachable")


class MissingLines(DeviceError):
    """A continuous scan in which no frame reached some lines."""


class NoFirstFrame(DeviceTimeout):
    """A streaming camera sent no frame after AcquisitionStart (the stage had not moved)."""


def scan_once(stage, camera, *, lines: int, samples: int, bands: int, pitch: int,
              start_position: int, t_ms: float, oversample: float = DEFAULT_OVERSAMPLE,
              max_blur_lines: float = MAX_BLUR_LINES, run_up_lines: int = RUN_UP_LINES,
              on_line: Callable[[int], None] | None = None,
              first_frame_s: float = FIRST_FRAME_S) -> tuple[np.ndarray, dict[str, Any]]:
    """One constant-velocity scan of ``lines`` lines at integration time ``t_ms``.

    Returns
    -------
    raw
        uint16 ``(lines, samples, bands)``.
    info
        ``mode``, ``frame_rate_hz``, ``speed_microsteps_per_s``, ``frames``,
        ``duplicate_frames``, ``max_offset_lines``, ``position_reads``,
        ``lost_buffers``.

    Raises
    ------
    MissingLines
        Lines no frame reached (lost frames, stage too fast), naming them.
    NoFirstFrame
        A streaming camera sent nothing within ``first_frame_s`` of AcquisitionStart
        (before the stage moved).
    """
    rate = _line_rate(camera, t_ms)
    # Frames per line: at least `oversample`, and enough that the slit moves at most
    # `max_blur_lines` during an exposure; an integer, so that with a phase-locked start
    # every m-th frame sits on a line centre.
    m = int(np.ceil(max(float(oversample), rate * t_ms / 1000.0 / float(max_blur_lines)) - 1e-9))
    m = max(m, 1)
    speed = max(1, int(round(pitch * rate / m)))
    run_up = int(run_up_lines) * int(pitch)
    p_from = max(0, int(start_position) - run_up)
    p_to = int(start_position) + (int(lines) - 1) * int(pitch) + run_up
    stage.move_abs(p_from)
    old_speed = _stage_speed(stage)
    # (the setting is in Zaber's speed unit, not microsteps/s)
    stage.query(f"set maxspeed {speed_setting(speed)}")
    positions: list[tuple[float, int]] = []
    lost0 = getattr(camera, "lost_buffers", 0)
    source = camera.stream(rate) if hasattr(camera, "stream") else _SerialStream(camera)
    timeout = 5.0 + 3.0 * (p_to - p_from) / speed
    n_frames = 0
    try:
        # the stage rests at p_from until the move below: frames before it lie there
        positions.append((time.time(), stage.position()))
        with source as s:
            if hasattr(camera, "stream"):
                # the camera must be streaming before the stage leaves the first line
                wait = max(float(first_frame_s), 20.0 / rate)
                t_first = time.time() + wait
                while not s.poll(0.01):
                    if time.time() > t_first:
                        raise NoFirstFrame(f"the camera sent no frame within {wait:.1f} s of "
                                           "AcquisitionStart", getattr(camera, "name", None))
            if hasattr(camera, "stream"):
                _wait_for_phase(stage, s.frames(), rate, lead_s=(int(start_position) - p_from) / speed)
            t0 = time.time()
            positions.append((t0, stage.position()))
            stage.move_abs(p_to, wait=False)
            while True:
                a = time.time()
                pos = stage.position()
                positions.append(((a + time.time()) / 2.0, pos))
                got = s.poll(0.002)   # also paces the position reads
                n_frames += len(got)
                if on_line is not None and got:
                    on_line(len(got))
                if pos >= p_to:
                    break
                if time.time() - t0 > timeout:
                    raise DeviceTimeout(f"continuous scan did not reach position {p_to} within "
                                        f"{timeout:.0f} s (stuck at {pos})", getattr(stage, "name", None))
            if hasattr(camera, "stream"):
                # Frames come in the order they were exposed, some late (a camera draining its
                # buffer after a stall): once one that began after the last position read is
                # in, all the scan needs is. Bounded, for a camera that stopped sending.
                t_last = positions[-1][0]
                t_end = time.time() + 2.0 / rate + LATE_FRAMES_S
                while time.time() < t_end:
                    s.poll(0.005)
                    newest = s.newest_start()
                    if newest is not None and newest > t_last:
                        break
            frames = s.frames()
            rate = s.rate or rate
    finally:
        if old_speed is not None:
            stage.query(f"set maxspeed {old_speed}")
    stage.wait_idle() if hasattr(stage, "wait_idle") else None
    pt = np.array([p[0] for p in positions])
    pv = np.array([p[1] for p in positions], dtype=np.float64)
    tf = np.array([f.t for f in frames], dtype=np.float64)
    u = (np.interp(tf, pt, pv) - start_position) / pitch
    u[(tf < pt[0]) | (tf > pt[-1])] = np.nan     # outside the position record: position unknown
    chosen, dups, offset = assign_frames(u, lines)
    missing = np.flatnonzero(chosen < 0)
    info = {"mode": "continuous", "frame_rate_hz": round(float(rate), 3), "speed_microsteps_per_s": speed,
            "frames_per_line": m, "frames": len(frames), "duplicate_frames": dups,
            "missing_lines": int(missing.size), "position_reads": len(positions),
            "lost_buffers": int(getattr(camera, "lost_buffers", 0) - lost0),
            "max_offset_lines": None if missing.size == lines else round(float(np.nanmax(offset)), 3)}
    if missing.size:
        raise MissingLines(f"continuous scan missed {missing.size} of {lines} lines ({_ranges(missing)}): "
                          f"{info['lost_buffers']} frames lost, {len(frames)} received at "
                          f"{info['frame_rate_hz']} Hz; lines are never filled in (rescan, raise "
                          "--oversample, or use --scan step)", getattr(camera, "name", None))
    raw = np.empty((lines, samples, bands), dtype=np.uint16)
    for k, f in enumerate(chosen):
        line = frames[f].line
        if line.shape != (samples, bands):
            raise DeviceError(f"camera sent a {line.shape} line, expected {(samples, bands)}",
                              getattr(camera, "name", None))
        raw[k] = line
    return raw, info
