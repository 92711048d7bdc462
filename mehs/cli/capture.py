"""`mehs capture` — capture a bracketed scene (dark/white references + exposures) into a scene folder."""

from __future__ import annotations


def configure(parser):
    from mehs.cli.sim_device import add_scene_arguments

    parser.add_argument("--stage", help="stage port: /dev/ttyUSB0, socket://host:port, …")
    parser.add_argument("--camera", help="camera port: /dev/ttyUSB1, socket://host:port, …")
    parser.add_argument("--out", required=True, help="scene folder to create (or to finish with --resume)")
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--times", help="integration times in ms, ascending, e.g. 5,20,80")
    g.add_argument("--auto", action="store_true", help="choose three times by auto-exposure (default)")
    parser.add_argument("--resume", action="store_true",
                        help="finish an interrupted scene without redoing completed exposures")
    parser.add_argument("--scene-id", help="scene id (default: the folder name)")
    parser.add_argument("--lines", type=int, default=None,
                        help="lines to scan (default 512, or the simulated scene's)")
    parser.add_argument("--pitch", type=int, default=64, help="stage microsteps per line (default 64)")
    parser.add_argument("--start-position", type=int, default=0, help="stage position of line 0")
    parser.add_argument("--dark-lines", type=int, default=16, help="lines averaged per dark reference")
    parser.add_argument("--white-lines", type=int, default=16,
                        help="lines averaged per white reference (0 = none)")
    parser.add_argument("--white-line", type=int, default=None,
                        help="scan line where the white tile starts (default lines+4)")
    parser.add_argument("--checksum", action="store_true", help="use Zaber message checksums")
    parser.add_argument("--timeout", type=float, default=2.0, help="reply timeout in seconds")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--simulate", action="store_true",
                        help="start the simulated stage and camera in-process (loopback TCP); "
                             "the scene folder then also gets truth/radiance.hdr")
    add_scene_arguments(parser, geometry=False)


def run(args):
    import sys

    from mehs.capture.camera import LineCamera
    from mehs.capture.session import capture_scene
    from mehs.capture.zaber import ZaberStage
    from mehs.errors import InputError

    times = None
    if args.times:
        try:
            times = [float(v) for v in args.times.replace(" ", "").split(",") if v]
        except ValueError:
            raise InputError(f"--times must be comma-separated numbers, got {args.times!r}") from None
    if not args.resume:  # the id `mehs build` will use: refuse now what it would refuse later
        from pathlib import Path

        from mehs.dataset.scene_list import check_scene_id

        check_scene_id(args.scene_id or Path(args.out).resolve().name)
    sim_options = _sim_options(args) if args.simulate else None
    if args.resume and args.simulate:
        _check_same_simulated_scene(args.out, sim_options)
    dev = None
    if args.simulate:
        from mehs.cli.sim_device import build_devices

        dev = build_devices(args).start()
        stage_url, camera_url = dev.stage_url, dev.camera_url
        lines = args.lines or dev.scene_lines
    else:
        if not (args.stage and args.camera):
            raise InputError("give --stage and --camera ports (or --simulate)")
        stage_url, camera_url = args.stage, args.camera
        lines = args.lines or 512
    stage = camera = None
    try:
        stage = ZaberStage.open(stage_url, timeout=args.timeout, checksum=args.checksum)
        camera = LineCamera.open(camera_url, timeout=args.timeout)
        info = {"simulated": bool(args.simulate)}
        if args.simulate:
            info["scene"] = dev.world.scene.info
            info["sim_options"] = sim_options
        doc = capture_scene(
            stage, camera, args.out, times_ms=times, auto=times is None and not args.resume,
            lines=lines, pitch=args.pitch, start_position=args.start_position,
            dark_lines=args.dark_lines, white_lines=args.white_lines,
            white_start_line=args.white_line, scene_id=args.scene_id, resume=args.resume,
            progress=not args.no_progress and sys.stderr.isatty(),
            seed=args.seed if args.simulate else None, device_info=info,
            log=lambda m: print(m, file=sys.stderr), resume_hint=_resume_hint(args))
        if args.simulate and doc["truth"] is None and all(
                e["status"] == "complete" for e in doc["exposures"]):
            from mehs.capture.simulate import motion_phase, write_truth

            scene = dev.world.scene
            t0 = doc["exposures"][0]["integration_time_ms"]
            write_truth(args.out, doc, scene.radiance_at(motion_phase(t0) if scene.moving else 0),
                        scene.wavelengths, fwhm=scene.fwhm,
                        dn_per_ms=dev.world.sensor.signal_scale(scene.wavelengths.size, scene.wavelengths))
    finally:
        for d in (stage, camera):
            if d is not None:
                d.close()
        if dev is not None:
            dev.close()
    done = [e for e in doc["exposures"] if e["status"] == "complete"]
    print(f"{args.out}: {len(done)} of {len(doc['plan']['times_ms'])} exposures complete "
          f"({', '.join(str(e['integration_time_ms']) for e in done)} ms)")
    return 0


#: Options of --simulate that decide what the simulated scene looks like.
_SIM_KEYS = ("scene", "size", "seed", "motion", "source_ratio", "response")


def _sim_options(args) -> dict:
    return {k: getattr(args, k, None) for k in _SIM_KEYS}


def _check_same_simulated_scene(out, options: dict) -> None:
    """Refuse to finish a simulated scene with another simulated scene's exposures."""
    from pathlib import Path

    from mehs.capture.scenefolder import read_scene_json
    from mehs.errors import InputError

    if not (Path(out) / "scene.json").is_file():
        return  # capture_scene says there is nothing to resume
    recorded = (read_scene_json(out).get("device") or {}).get("sim_options")
    if recorded is None:
        return  # captured before the options were recorded (or on real devices)
    differ = {k: (recorded.get(k), options.get(k)) for k in _SIM_KEYS
              if recorded.get(k) != options.get(k)}
    if differ:
        was = " ".join(f"--{k.replace('_', '-')} {v[0]}" for k, v in differ.items())
        raise InputError(f"this scene was simulated with other options ({was}); resuming "
                         "with these would mix two scenes in one bracket", out)


def _resume_hint(args) -> str:
    """The command that finishes this capture: the same devices or simulated scene."""
    import shlex

    parts = ["mehs", "capture", "--resume", "--out", str(args.out)]
    if args.simulate:
        parts.append("--simulate")
        defaults = {"scene": "colorchecker", "size": 64, "seed": 0, "motion": False,
                    "source_ratio": 1000.0, "response": "linear"}
        for k, v in _sim_options(args).items():
            if v != defaults.get(k) and v is not None:
                flag = f"--{k.replace('_', '-')}"
                parts += [flag] if v is True else [flag, str(v)]
    else:
        parts += ["--stage", str(args.stage), "--camera", str(args.camera)]
    return " ".join(shlex.quote(p) for p in parts)
