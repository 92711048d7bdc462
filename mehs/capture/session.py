"""Bracketed capture sessions: auto-exposure, references and line scans into a scene folder.

One scene = for each integration time ``t_k`` (shortest first): a dark
reference at ``t_k`` (shutter closed, ``dark_lines`` lines averaged), a white
reference at ``t_k`` (``white_lines`` lines of the white tile averaged) and the
scan of ``lines`` lines, stage and camera stepping together. Each exposure is
written as a Specim IQ folder and recorded in ``scene.json``
(:mod:`mehs.capture.scenefolder`).

No data lost: ``scene.json`` marks an exposure ``incomplete`` before its first
line and ``complete`` only after its folder is in place and hashed; the folder
itself is assembled under a temporary name and renamed. ``resume=True``
re-checks the SHA-256 of completed exposures, keeps them, and captures only
the rest. An existing raw capture is never overwritten (a stray folder of an
exposure that was never marked complete is moved aside, not deleted).
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from mehs.capture import scenefolder as sf
from mehs.capture.simulate import WHITE_GAP_LINES
from mehs.errors import DeviceError, InputError, MehsError

#: Auto-exposure: at most this fraction of samples may be at or above ``SAT_LEVEL`` × full scale.
MAX_SATURATED_FRACTION = 1e-4
SAT_LEVEL = 0.98
#: ``scan=`` values of :func:`capture_scene`.
SCAN_MODES = ("step", "continuous")


class Scanner:
    """Stage + camera stepping together; every read goes through the drivers' retry policies."""

    def __init__(self, stage, camera, *, pitch: int = sf.DEFAULT_PITCH, start_position: int = 0):
        self.stage, self.camera = stage, camera
        self.pitch, self.start_position = int(pitch), int(start_position)
        self._known_pos: int | None = None

    def position_of(self, line: int) -> int:
        return self.start_position + int(line) * self.pitch

    def goto(self, line: int) -> int:
        target = self.position_of(line)
        self.stage.move_abs(target)
        self._known_pos = target
        return target

    def read(self, line: int) -> np.ndarray:
        """uint16 ``(samples, bands)`` at scan line ``line``."""
        self.goto(line)
        return self.camera.read_line()

    def read_lines(self, lines: Sequence[int]) -> np.ndarray:
        """uint16 ``(len(lines), samples, bands)``: the lines as the camera sent them."""
        return np.stack([self.read(ln) for ln in lines])

    def read_mean(self, lines: Sequence[int]) -> np.ndarray:
        acc = None
        for ln in lines:
            z = self.read(ln).astype(np.float64)
            acc = z if acc is None else acc + z
        return (acc / len(lines)).astype(np.float32)


# --------------------------------------------------------------------------- auto exposure
def auto_exposure(scanner: Scanner, *, lines: int, n: int = 3, probe_lines: int = 16,
                  t_start_ms: float = 1.0, t_min_ms: float = 0.01, t_max_ms: float = 2000.0,
                  bit_depth: int = 12, min_ratio: float = 4.0, target_snr: float = 10.0,
                  max_iterations: int = 12, max_step: float | None = None
                  ) -> tuple[list[float], dict[str, Any]]:
    """Choose ``n`` integration times from quick probe scans.

    - **shortest**: the longest time with at most :data:`MAX_SATURATED_FRACTION`
      of probe samples at DN ≥ 0.98·full scale, found by scaling from the
      measured peak rate and bisecting in log-time;
    - **longest**: the time at which the darkest decile of probe samples sits
      ``target_snr`` × the dark noise (at least 1 % of full scale) above the dark
      level, at least ``min_ratio`` × the shortest, at most ``t_max_ms``;
    - the others geometric in between; with ``max_step`` (a response ladder)
      as many as needed for consecutive times at most ``max_step`` apart, at
      least ``n``.

    ``probe_lines`` scan lines spread over the scene are read at each trial
    time; the dark level and noise come from shutter-closed lines at the same
    time. Returns ``(times_ms ascending, info)``.
    """
    cam = scanner.camera
    full = float((1 << int(bit_depth)) - 1)
    rows = np.unique(np.linspace(0, lines - 1, min(probe_lines, lines)).round().astype(int)).tolist()
    history: list[dict[str, float]] = []

    def probe(t: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        t = cam.set_integration_time(t)
        cam.set_shutter(False)
        darks = np.stack([scanner.read(r).astype(np.float32) for r in rows[:4]])
        cam.set_shutter(True)
        z = np.stack([scanner.read(r).astype(np.float32) for r in rows])
        dark = darks.mean(axis=0)
        noise = float(np.median(darks.std(axis=0))) if len(darks) > 1 else 1.0
        return z, dark, noise, t

    t = float(np.clip(t_start_ms, t_min_ms, t_max_ms))
    t_good, t_bad = None, None
    info: dict[str, Any] = {"probe_lines": rows, "history": history}
    for _ in range(max_iterations):
        z, dark, noise, t = probe(t)
        sat = float(np.mean(z >= SAT_LEVEL * full))
        sig = z - dark[None]
        peak = float(np.quantile(sig, 1 - MAX_SATURATED_FRACTION))
        history.append({"t_ms": t, "saturated_fraction": sat, "peak_dn": peak})
        if sat > MAX_SATURATED_FRACTION:
            t_bad = t
            if t <= t_min_ms:
                info["warning"] = "saturates even at the shortest integration time"
                t_good = t
                break
            t = max(t_min_ms, np.sqrt(t * t_good) if t_good else t / 8.0)
            continue
        t_good = t
        target = 0.8 * (SAT_LEVEL * full - float(dark.mean()))
        if peak >= 0.5 * target or t >= t_max_ms:
            break
        t_next = t * min(target / max(peak, 1.0), 64.0)
        if t_bad is not None:
            t_next = min(t_next, np.sqrt(t * t_bad))
        if t_next <= t * 1.05:
            break
        t = min(t_next, t_max_ms)
    t_short = float(t_good if t_good is not None else t_min_ms)

    # Longest: the darkest decile above the noise floor.
    t = min(t_short * 16.0, t_max_ms)
    t_long = t
    for _ in range(4):
        z, dark, noise, t = probe(t)
        useful = max(target_snr * max(noise, 0.5), 0.01 * full)
        p10 = float(np.quantile(z - dark[None], 0.10))
        history.append({"t_ms": t, "darkest_decile_dn": p10, "useful_dn": useful})
        info["useful_dn"] = useful
        if p10 <= 0.5:
            if t >= t_max_ms:
                t_long = t_max_ms
                break
            t = min(t * 16.0, t_max_ms)
            continue
        t_long = min(t * useful / p10, t_max_ms)
        if abs(np.log(t_long / t)) < np.log(1.5):
            break
        t = t_long
    t_long = float(np.clip(t_long, t_short * min_ratio, max(t_max_ms, t_short * min_ratio)))
    if max_step is not None:
        if not max_step > 1:
            raise InputError(f"ladder step must be > 1, got {max_step}")
        n = max(int(n), int(np.ceil(np.log(t_long / t_short) / np.log(max_step) - 1e-9)) + 1)
    times = np.geomspace(t_short, t_long, n) if n > 1 else np.array([t_short])
    times = [float(f"{v:.3g}") for v in times]
    info.update(t_short_ms=times[0], t_long_ms=times[-1])
    return times, info


# --------------------------------------------------------------------------- capture
def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="line", disable=not enabled, leave=False, dynamic_ncols=True)


def _check_times(times: Sequence[float]) -> list[float]:
    t = [float(v) for v in times]
    if not t or any(not (np.isfinite(v) and v > 0) for v in t):
        raise InputError(f"integration times must be positive numbers, got {list(times)}")
    if any(b <= a for a, b in zip(t, t[1:])):
        raise InputError(f"integration times must be strictly ascending, got {t}")
    return t


def _check_times_on_camera(camera, times: Sequence[float]) -> None:
    """Ask the camera to accept each planned time before anything is written.

    A time the camera refuses (e.g. 99999 ms) would otherwise stop the capture after the
    first exposures, leaving a scene whose plan can never be finished by ``--resume``.
    """
    for t in times:
        try:
            camera.set_integration_time(t)
        except DeviceError as exc:
            raise InputError(f"the camera does not accept an integration time of "
                             f"{sf.format_time_ms(t)} ms ({exc.problem}); nothing was "
                             "captured or written") from None


def _default_hint(out: Path) -> str:
    return f"mehs capture --resume --out {out} --stage PORT --camera PORT"


def remove_partial_writes(scene_dir: Path) -> list[str]:
    """Remove ``exposures/.<name>.part-*`` folders (and ``.scene.json.*.part*`` files) left
    by a kill during an exposure write.

    They are never complete (an exposure folder is renamed into place only when
    written), so nothing of value is lost; returns the removed names.
    """
    gone = []
    exp = Path(scene_dir) / "exposures"
    if exp.is_dir():
        for p in sorted(exp.glob(".*.part-*")):
            shutil.rmtree(p, ignore_errors=True)
            gone.append(p.name)
    for p in sorted(Path(scene_dir).glob(f".{sf.SCENE_JSON}.*.part*")):  # atomic-write temps
        p.unlink(missing_ok=True)
        gone.append(p.name)
    return gone


def _lock_file(name: str) -> bool:
    """Whether ``name`` is the output lock ``mehs capture`` holds on the scene folder (or
    its temporary): it does not make the folder a capture's."""
    from mehs.io.lock import LOCK_NAME

    return name == LOCK_NAME or name.startswith(f"{LOCK_NAME}.")


def _move_aside(path: Path) -> Path:
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    dest = path.with_name(f".orphan-{path.name}-{stamp}")
    os.replace(path, dest)
    return dest


def capture_scene(stage, camera, out_dir: str | Path, *, times_ms: Sequence[float] | None = None,
                  auto: bool = False, lines: int | None = None, pitch: int = sf.DEFAULT_PITCH,
                  start_position: int = 0, dark_lines: int = 16, white_lines: int = 16,
                  white_start_line: int | None = None, scene_id: str | None = None,
                  resume: bool = False, progress: bool = True, seed: int | None = None,
                  device_info: dict | None = None, auto_options: dict | None = None,
                  resume_hint: str | None = None,
                  log: Callable[[str], None] | None = None, scan: str = "step",
                  scan_options: dict | None = None) -> dict[str, Any]:
    """Capture (or finish, with ``resume=True``) a bracketed scene into ``out_dir``.

    Parameters
    ----------
    stage, camera
        Connected drivers (:class:`~mehs.capture.zaber.ZaberStage`,
        :class:`~mehs.capture.camera.LineCamera`) or objects with the same methods.
    times_ms, auto
        Explicit ascending integration times, or ``auto=True`` for
        :func:`auto_exposure` (three times).
    lines, pitch, start_position
        Scan ``lines`` lines at stage positions ``start_position + i·pitch``.
    dark_lines, white_lines, white_start_line
        Reference sizes; the white tile starts at scan line ``white_start_line``
        (default ``lines + 4``, where the simulator puts it); ``white_lines=0``
        skips the white reference.
    resume_hint
        The command that resumes this capture, quoted in error messages (default:
        ``mehs capture --resume --out OUT`` plus placeholders for the device options).
    resume
        Finish an interrupted scene: completed exposures are verified (SHA-256)
        and kept, the plan (times, geometry, scan mode) is read from ``scene.json``.
    scan
        ``"step"`` (stop-and-go: the stage stops on each line) or
        ``"continuous"`` (constant velocity, camera free-running:
        :func:`mehs.capture.scan.scan_continuous`, with ``scan_options`` such
        as ``oversample``). References are always taken stop-and-go.

    Returns
    -------
    dict
        The final ``scene.json`` document.

    Raises
    ------
    DeviceError
        A persistent device fault; ``scene.json`` then marks the partial
        exposure incomplete and the message says how to resume.
    """
    out = Path(out_dir)
    say = log or (lambda msg: None)
    if resume:
        doc = sf.read_scene_json(out)
        plan = doc.get("plan")
        if not isinstance(plan, dict) or "times_ms" not in plan:
            raise InputError("scene.json has no capture plan; cannot resume", out / sf.SCENE_JSON)
        for rec in doc["exposures"]:
            if rec["status"] == "complete":
                bad = sf.verify_exposure(out, rec)
                if bad:
                    raise InputError(f"completed exposure {rec['folder']} no longer matches its "
                                     f"SHA-256 ({', '.join(bad[:3])}); refusing to resume over it", out)
        for name in remove_partial_writes(out):
            say(f"removed an unfinished exposure write {name}")
        lines, pitch, start_position = plan["lines"], plan["pitch"], plan["start_position"]
        dark_lines, white_lines = plan["dark_lines"], plan["white_lines"]
        white_start_line = plan["white_start_line"]
        scan = plan.get("scan", "step")
        scan_options = plan.get("scan_options") or {}
    else:
        sf.refuse_new_capture_into(out)
        if out.is_dir():
            # a capture killed while it wrote its first scene.json left only the temporary
            for p in out.glob(f".{sf.SCENE_JSON}.*.part*"):
                p.unlink(missing_ok=True)
        if out.exists() and any(not _lock_file(p.name) for p in out.iterdir()):
            raise InputError("output folder exists and is not empty", out)
        if lines is None or int(lines) < 1:
            raise InputError(f"number of scan lines must be >= 1, got {lines}")
        # the stage would reject the first move only after scene.json was written
        if int(pitch) < 1:
            raise InputError(f"stage pitch must be >= 1 microstep per line, got {pitch}")
        if int(start_position) < 0:
            raise InputError(f"stage start position must be >= 0, got {start_position}")
        if (times_ms is None) == (not auto):
            raise InputError("give either integration times or auto=True")
        if dark_lines < 1:
            raise InputError(f"dark_lines must be >= 1, got {dark_lines}")
        if scan not in SCAN_MODES:
            raise InputError(f"scan mode must be one of {', '.join(SCAN_MODES)}, got {scan!r}")
        if times_ms is not None:
            _check_times(times_ms)  # before the stage is homed or the camera touched
        lines = int(lines)
        white_start_line = lines + WHITE_GAP_LINES if white_start_line is None else int(white_start_line)

    scanner = Scanner(stage, camera, pitch=pitch, start_position=start_position)
    # Devices: faults stop here with a clear message; an un-homed stage is homed (not a scan move).
    warns = stage.warnings()
    faults = [w for w in warns if w.startswith("F")]
    if faults:
        raise DeviceError(f"stage reports fault(s) {faults}; clear them (Zaber 'warnings clear') "
                          "after checking the mechanics", stage.name)
    if "WR" in warns:
        say("stage not homed: homing")
        stage.home()
    samples, bands = camera.shape()
    wavelengths = camera.wavelengths()
    if wavelengths.size != bands:
        raise DeviceError(f"camera reports {wavelengths.size} wavelengths for {bands} bands", camera.name)
    try:
        fwhm = camera.fwhm()
        if fwhm.size != bands:
            fwhm = None
    except DeviceError:
        fwhm = None
    bit_depth = camera.bit_depth()
    full = (1 << bit_depth) - 1
    if resume:
        cam_doc = doc.get("device", {}).get("camera", {})
        same = (cam_doc.get("samples", samples) == samples and cam_doc.get("bands", bands) == bands
                and len(doc["wavelengths"]) == bands
                and np.allclose(doc["wavelengths"], wavelengths, atol=0.01))
        if not same:
            raise DeviceError(f"this camera ({samples} samples × {bands} bands) is not the one that "
                              f"captured {out}; refusing to mix exposures", camera.name)

    if not resume:
        auto_info = None
        if auto:
            times, auto_info = auto_exposure(scanner, lines=lines, bit_depth=bit_depth,
                                             **(auto_options or {}))
            say(f"auto-exposure: {', '.join(sf.format_time_ms(t) for t in times)} ms")
        else:
            times = _check_times(times_ms)
            _check_times_on_camera(camera, times)  # before scene.json exists, not half-way
        doc = sf.new_scene_doc(scene_id or out.name, wavelengths, seed=seed,
                               device={"stage": {"url": stage.name}, "camera": {
                                   "url": camera.name, "id": camera.identify(),
                                   "samples": samples, "bands": bands, "bit_depth": bit_depth},
                                   **(device_info or {})})
        doc["plan"] = {"times_ms": times, "lines": lines, "pitch": pitch,
                       "start_position": start_position, "dark_lines": dark_lines,
                       "white_lines": white_lines, "white_start_line": white_start_line,
                       "auto_exposure": auto_info, "scan": scan,
                       "scan_options": dict(scan_options or {})}
        doc["white_reference"] = ({"lines": white_lines, "start_line": white_start_line,
                                   "start_position": scanner.position_of(white_start_line)}
                                  if white_lines else {})
        out.mkdir(parents=True, exist_ok=True)
        sf.write_scene_json(out, doc)
    times = [float(t) for t in doc["plan"]["times_ms"]]

    by_index = {rec["index"]: i for i, rec in enumerate(doc["exposures"])}
    for k, t_req in enumerate(times):
        if k in by_index and doc["exposures"][by_index[k]]["status"] == "complete":
            say(f"exposure {k}: complete, kept")
            continue
        t_act = camera.set_integration_time(t_req)
        name = sf.exposure_folder_name(k, t_act)
        folder = out / "exposures" / name
        if folder.exists():
            moved = _move_aside(folder)
            say(f"exposure {k}: moved an unrecorded folder aside to {moved.name}")
        rec: dict[str, Any] = {"index": k, "folder": f"exposures/{name}",
                               "requested_integration_time_ms": t_req, "integration_time_ms": t_act,
                               "status": "incomplete", "started": sf.now_iso(), "lines_done": 0,
                               "files": {}}
        if k in by_index:
            doc["exposures"][by_index[k]] = rec
        else:
            by_index[k] = len(doc["exposures"])
            doc["exposures"].append(rec)
        doc["exposures"].sort(key=lambda r: r["index"])
        by_index = {r["index"]: i for i, r in enumerate(doc["exposures"])}
        sf.write_scene_json(out, doc)
        try:
            raw, dark, white, st = _scan_exposure(scanner, k, t_act, lines=lines, samples=samples,
                                                  bands=bands, dark_lines=dark_lines,
                                                  white_lines=white_lines,
                                                  white_start_line=white_start_line,
                                                  progress=progress, rec=rec, scan=scan,
                                                  scan_options=scan_options)
            extra = {"frame_rate_hz": camera.frame_rate(), "temperature_c": camera.temperature(),
                     "saturation_fraction": float(np.count_nonzero(raw >= full) / raw.size),
                     "stage": st, "started": rec["started"], "lines_done": lines,
                     "device_events": stage.events[-20:] + camera.events[-20:]}
            stage.events.clear()
            camera.events.clear()
            final = sf.write_exposure(out, k, t_act, raw, dark, white, wavelengths=wavelengths,
                                      fwhm=fwhm, requested_ms=t_req, extra=extra,
                                      started=rec["started"])
        except (MehsError, KeyboardInterrupt) as exc:
            rec["status"] = "incomplete"
            rec["error"] = f"{type(exc).__name__}: {exc}"
            rec["device_events"] = stage.events[-20:] + camera.events[-20:]
            sf.write_scene_json(out, doc)
            if isinstance(exc, KeyboardInterrupt):
                raise
            raise DeviceError(f"exposure {k} ({sf.format_time_ms(t_act)} ms) stopped after "
                              f"{rec['lines_done']} of {lines} lines: {exc}. Completed exposures "
                              f"are kept; finish with '{resume_hint or _default_hint(out)}'",
                              None) from exc
        doc["exposures"][by_index[k]] = final
        sf.write_scene_json(out, doc)
        say(f"exposure {k}: {sf.format_time_ms(t_act)} ms complete, "
            f"saturated {final['saturation_fraction']:.4%}")
    return doc


def _scan_exposure(scanner: Scanner, k: int, t: float, *, lines: int, samples: int, bands: int,
                   dark_lines: int, white_lines: int, white_start_line: int, progress: bool,
                   rec: dict, scan: str = "step", scan_options: dict | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict]:
    cam, stage = scanner.camera, scanner.stage
    # Dark reference at this time: shutter closed, stepping so each line is a new frame.
    # The lines are kept as sent (a reader averages them): one rounded mean line would
    # carry a ±0.5 DN error into every dark-subtracted sample of its column and band.
    cam.set_shutter(False)
    dark = scanner.read_lines(range(dark_lines))
    cam.set_shutter(True)
    white = None
    if white_lines:
        white = scanner.read_lines(range(white_start_line, white_start_line + white_lines))
    if scan == "continuous":
        from mehs.capture.scan import scan_continuous

        with _progress(lines, f"exposure {k} ({sf.format_time_ms(t)} ms, continuous)", progress) as bar:
            raw, info = scan_continuous(stage, cam, lines=lines, samples=samples, bands=bands,
                                        pitch=scanner.pitch, start_position=scanner.start_position,
                                        t_ms=t, on_line=bar.update, **(scan_options or {}))
        rec["lines_done"] = lines
        return raw, dark, white, {"start_position": scanner.start_position,
                                  "end_position": stage.position(), "warnings": stage.warnings(),
                                  "scan": info}
    raw = np.empty((lines, samples, bands), dtype=np.uint16)
    with _progress(lines, f"exposure {k} ({sf.format_time_ms(t)} ms)", progress) as bar:
        start = scanner.goto(0)
        for i in range(lines):
            line = scanner.read(i)
            if line.shape != (samples, bands):
                raise DeviceError(f"camera sent a {line.shape} line, expected {(samples, bands)}",
                                  cam.name)
            raw[i] = line
            rec["lines_done"] = i + 1
            bar.update(1)
    end = stage.position()
    warnings = stage.warnings()
    return raw, dark, white, {"start_position": start, "end_position": end, "warnings": warnings}
