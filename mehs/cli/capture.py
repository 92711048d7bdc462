"""`mehs capture` — capture a bracketed scene (dark/white references + exposures) into a scene folder."""

from __future__ import annotations


def configure(parser):
    from mehs.cli.sim_device import add_scene_arguments

    parser.add_argument("--stage", help="stage port: /dev/ttyUSB0, socket://host:port, …")
    parser.add_argument("--camera", help="camera: serial port (/dev/ttyUSB1, socket://host:port, …) "
                                         "or a GenICam camera through Aravis (aravis://DEVICE-ID, "
                                         "genicam://DEVICE-ID)")
    parser.add_argument("--out", help="scene folder to create (or to finish with --resume)")
    parser.add_argument("--list-cameras", action="store_true",
                        help="list the GenICam cameras (GigE Vision, USB3 Vision) Aravis finds, and exit")
    parser.add_argument("--scan", choices=["step", "continuous"], default="step",
                        help="step: the stage stops on every line (default); continuous: constant "
                             "velocity, the camera free-running at a matching frame rate")
    parser.add_argument("--oversample", type=float, default=None,
                        help="--scan continuous: at least this many frames per line pitch (default 2: "
                             "a lost frame costs no line; 1 is fastest)")
    parser.add_argument("--dark-prompt", action="store_true",
                        help="GenICam camera without a shutter feature: ask on the terminal to cap / "
                             "uncap the lens for the dark references")
    parser.add_argument("--wavelengths", metavar="FILE",
                        help="GenICam camera: band centres in nm (one per band) when the camera does "
                             "not report its spectral calibration")
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--times", help="integration times in ms, ascending, e.g. 5,20,80")
    g.add_argument("--auto", action="store_true", help="choose three times by auto-exposure (default)")
    g.add_argument("--ladder", action="store_true",
                   help="a response ladder: auto-exposure range in >= 5 steps of at most x4, "
                        "of a static target; fuse it with --response debevec once and reuse "
                        "its response.json (--response) for wide brackets")
    parser.add_argument("--resume", action="store_true",
                        help="finish an interrupted scene without redoing completed exposures")
    parser.add_argument("--scene-id", help="scene id (default: the folder name)")
    parser.add_argument("--lines", type=int, default=None,
                        help="lines to scan (default 512, or the simulated scene's)")
    parser.add_argument("--pitch", type=int, default=64, help="stage microsteps per line (default 64)")
    parser.add_argument("--start-position", type=int, default=0,
                        help="stage position of line 0 (default 0)")
    parser.add_argument("--dark-lines", type=int, default=16,
                        help="shutter-closed lines per dark reference, stored as read and "
                             "averaged when fused (default 16)")
    parser.add_argument("--white-lines", type=int, default=16,
                        help="white-tile lines per white reference, stored as read (0 = none; "
                             "default 16)")
    parser.add_argument("--white-line", type=int, default=None,
                        help="scan line where the white tile starts (default lines+4)")
    parser.add_argument("--checksum", action="store_true",
                        help="use Zaber message checksums (the stage must have comm.checksum = 1: "
                             "'/set comm.checksum 1' once; with --simulate the simulated stage "
                             "is set so)")
    parser.add_argument("--no-message-ids", action="store_true",
                        help="send Zaber commands without message ids (a device that does not "
                             "echo them); with ids a late reply is recognised and dropped")
    parser.add_argument("--timeout", type=float, default=2.0,
                        help="reply timeout in seconds (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--simulate", action="store_true",
                        help="start the simulated stage and camera in-process (loopback TCP); "
                             "the scene folder then also gets truth/radiance.hdr")
    parser.add_argument("--genicam", action="store_true",
                        help="with --simulate: the simulated camera is a GigE Vision camera on "
                             "127.0.0.1 (needs Aravis)")
    add_scene_arguments(parser, geometry=False)


def run(args):
    import sys
    from pathlib import Path

    from mehs.capture.session import capture_scene
    from mehs.capture.zaber import ZaberStage
    from mehs.errors import InputError

    if args.list_cameras:
        return _list_cameras()
    if not args.out:
        raise InputError("give --out SCENE_FOLDER (or --list-cameras)")

    times = None
    if args.times:
        try:
            times = [float(v) for v in args.times.replace(" ", "").split(",") if v]
        except ValueError:
            raise InputError(f"--times must be comma-separated numbers, got {args.times!r}") from None
        if len(times) < 2:
            # fuse, build and calibrate all refuse a one-exposure scene: refuse it now,
            # before the stage moves, not after a capture nothing can use
            raise InputError(f"--times needs two or more integration times for a bracket, got "
                             f"{args.times!r} (e.g. --times 5,20,80; or --auto)")
    if not args.resume:  # the id `mehs build` will use: refuse now what it would refuse later
        from mehs.dataset.scene_list import check_scene_id

        check_scene_id(args.scene_id or Path(args.out).resolve().name)
    from mehs.cli._overwrite import check_writable

    check_writable(args.out)  # before the devices start and the stage moves
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError("output folder exists and is not a folder", args.out)
    if not args.resume:
        # before the lock below is taken: even its lock file would change a raw capture
        # (a --resume finishes its own scene folder, lock and all)
        from mehs.capture.scenefolder import refuse_new_capture_into

        refuse_new_capture_into(args.out)
    sim_options = _sim_options(args) if args.simulate else None
    if args.resume and args.simulate:
        _check_same_simulated_scene(args.out, sim_options)
    dev = None
    if args.simulate:
        from mehs.cli.sim_device import build_devices

        # the simulated stage is set up as a real one used with --checksum must be
        # ('/set comm.checksum 1'), so that its replies carry checksums too
        dev = build_devices(args, genicam=args.genicam, comm_checksum=args.checksum).start()
        stage_url, camera_url = dev.stage_url, dev.camera_url
        lines = args.lines or dev.scene_lines
    else:
        if not (args.stage and args.camera):
            raise InputError("give --stage and --camera ports (or --simulate)")
        stage_url, camera_url = args.stage, args.camera
        lines = args.lines or 512
    stage = camera = lock = None
    try:
        from mehs.io.lock import OutputLock

        # two captures (or a capture and a --resume) into one scene folder would both pass
        # the "no scene.json yet" check and write each other's exposures: the second is
        # refused, naming the first; a killed capture's lock is taken over
        lock = OutputLock(args.out, what="mehs capture").__enter__()
        stage = ZaberStage.open(stage_url, timeout=args.timeout, checksum=args.checksum,
                                message_ids=not args.no_message_ids)
        camera = open_camera(camera_url, args)
        info = {"simulated": bool(args.simulate)}
        if args.simulate:
            info["scene"] = dev.world.scene.info
            info["sim_options"] = sim_options
        doc = capture_scene(
            stage, camera, args.out, times_ms=times, auto=times is None and not args.resume,
            lines=lines, pitch=args.pitch, start_position=args.start_position,
            dark_lines=args.dark_lines, white_lines=args.white_lines,
            white_start_line=args.white_line, scene_id=args.scene_id, resume=args.resume, scan=args.scan,
            scan_options={"oversample": args.oversample} if args.oversample else None,
            progress=not args.no_progress and sys.stderr.isatty(),
            seed=args.seed if args.simulate else None, device_info=info,
            auto_options={"n": 5, "max_step": 4.0} if args.ladder else None,
            log=lambda m: print(m, file=sys.stderr), resume_hint=_resume_hint(args))
        if args.simulate and all(e["status"] == "complete" for e in doc["exposures"]):
            # each piece of the truth is written unless scene.json records it, so that a
            # --resume after a kill between two of them (or between a file and its record)
            # finishes them; an unrecorded file is a killed run's and is replaced (the truth
            # is the simulator's, not a capture)
            from mehs.capture.simulate import motion_phase, write_moved_mask, write_truth

            scene = dev.world.scene
            t0 = doc["exposures"][0]["integration_time_ms"]
            if doc["truth"] is None:
                write_truth(args.out, doc,
                            scene.radiance_at(motion_phase(t0) if scene.moving else 0),
                            scene.wavelengths, fwhm=scene.fwhm, overwrite=True,
                            dn_per_ms=dev.world.sensor.signal_scale(scene.wavelengths.size,
                                                                    scene.wavelengths))
            if scene.moving and doc.get("truth_moved_mask") is None:
                # the truth is the first exposure's radiance: say where the others differ
                phases = [motion_phase(e["integration_time_ms"]) for e in doc["exposures"]]
                write_moved_mask(args.out, doc, scene.moved_between(phases), overwrite=True)
            if scene.info.get("certificate") and not (
                    Path(args.out) / scene.info["certificate"]).is_file():
                # a simulated calibrated source comes with its certificate, as a real one does
                from mehs.calibration.targets import sphere_certificate

                sphere_certificate(Path(args.out) / scene.info["certificate"],
                                   scene.info.get("level", 0.5))
    finally:
        for d in (stage, camera):
            if d is not None:
                d.close()
        if dev is not None:
            dev.close()
        if lock is not None:
            lock.__exit__(*sys.exc_info())
    done = [e for e in doc["exposures"] if e["status"] == "complete"]
    print(f"{args.out}: {len(done)} of {len(doc['plan']['times_ms'])} exposures complete "
          f"({', '.join(str(e['integration_time_ms']) for e in done)} ms)")
    return 0


def _prompt(state: str) -> None:
    import sys

    from mehs.errors import InputError

    what = "Cap the lens (dark reference)" if state == "close" else "Uncap the lens"
    print(f"{what}, then press Enter: ", end="", file=sys.stderr, flush=True)
    if not sys.stdin.readline():
        raise InputError("--dark-prompt needs a terminal (stdin closed while waiting for Enter)")


def open_camera(url: str, args):
    """The camera driver for ``url``: GenICam (``aravis://``, ``genicam://``) or the serial line camera."""
    from mehs.capture.aravis import is_genicam_url
    from mehs.capture.genicam import GenicamCamera
    from mehs.capture.spectral_cal import read_calibration

    if is_genicam_url(url):
        cal = read_calibration(args.wavelengths) if args.wavelengths else None
        return GenicamCamera.open(url, timeout=args.timeout, wavelengths=cal,
                                  dark_prompt=_prompt if args.dark_prompt else None)
    from mehs.capture.camera import LineCamera

    return LineCamera.open(url, timeout=args.timeout)


def _list_cameras() -> int:
    from mehs.capture.aravis import list_cameras

    cams = list_cameras()
    if not cams:
        print("no GenICam cameras found (GigE Vision: same subnet, firewall open for UDP 3956; "
              "USB3 Vision: udev permissions)")
    for c in cams:
        print(f"aravis://{c['id']}  {c['vendor']} {c['model']}  serial {c['serial']}  "
              f"{c['protocol']} {c['address']}")
    return 0


#: Options of --simulate that decide what the simulated scene looks like (a natural scene's
#: lighting is drawn from --seed when not given, so --pool and --lighting change the scene too).
_SIM_KEYS = ("scene", "size", "seed", "motion", "source_ratio", "response", "pool", "lighting")

#: Their defaults (the resume hint gives only the options that differ).
_SIM_DEFAULTS = {"scene": "colorchecker", "size": 64, "seed": 0, "motion": False,
                 "source_ratio": 1000.0, "response": "linear", "pool": "all", "lighting": None}


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
    # scenes captured before --pool/--lighting were recorded: compare what was recorded
    differ = {k: (recorded.get(k), options.get(k)) for k in _SIM_KEYS
              if k in recorded and recorded.get(k) != options.get(k)}
    if differ:
        was = " ".join(_flag(k, v[0]) for k, v in differ.items())
        raise InputError(f"this scene was simulated with other options ({was}); resuming "
                         "with these would mix two scenes in one bracket", out)


def _flag(key: str, value) -> str:
    """An option as the user would have typed it (``no --lighting`` when it was not given)."""
    flag = f"--{key.replace('_', '-')}"
    if value is None or value is False:
        return f"no {flag}"
    return flag if value is True else f"{flag} {value}"


def _resume_hint(args) -> str:
    """The command that finishes this capture: the same devices or simulated scene."""
    import shlex

    parts = ["mehs", "capture", "--resume", "--out", str(args.out)]
    if args.simulate:
        parts.append("--simulate")
        if getattr(args, "genicam", False):
            parts.append("--genicam")
        for k, v in _sim_options(args).items():
            if v != _SIM_DEFAULTS.get(k) and v is not None:
                flag = f"--{k.replace('_', '-')}"
                parts += [flag] if v is True else [flag, str(v)]
    else:
        parts += ["--stage", str(args.stage), "--camera", str(args.camera)]
    # the link's options too: a stage that needs them refuses a resume without them
    parts += (["--checksum"] if getattr(args, "checksum", False) else []) + (
        ["--no-message-ids"] if getattr(args, "no_message_ids", False) else [])
    return " ".join(shlex.quote(p) for p in parts)
