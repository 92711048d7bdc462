"""`mehs sim-device` — serve the simulated stage and camera until killed.

Prints one ``name: value`` line per item (machine-readable), e.g.::

    stage: socket://127.0.0.1:40123
    camera: socket://127.0.0.1:40124
    lines: 64
    ready
"""

from __future__ import annotations


def add_scene_arguments(parser, *, geometry: bool = True) -> None:
    """Scene/sensor options shared by ``sim-device`` and ``capture --simulate``."""
    parser.add_argument("--scene", default="colorchecker",
                        help="simulated scene kind: colorchecker, lamp, window, ramp, natural "
                             "(measured materials and lights, mehs.scenes), or the calibration "
                             "targets sphere and panel (default colorchecker)")
    parser.add_argument("--pool", default="all", choices=["train", "val", "test", "all"],
                        help="natural scenes: the disjoint material/light pool drawn from (default all)")
    parser.add_argument("--lighting", default=None,
                        choices=["daylight", "tungsten", "fluorescent", "led", "sodium", "mixed"],
                        help="natural scenes: lighting setting (default: drawn from --seed)")
    parser.add_argument("--size", type=int, default=64,
                        help="scene size in lines and samples (default 64; 512 = Specim IQ)")
    if geometry:
        parser.add_argument("--lines", dest="scene_lines", type=int, default=None,
                            help="scene lines (default --size)")
        parser.add_argument("--samples", dest="scene_samples", type=int, default=None,
                            help="scene samples (default --size)")
    parser.add_argument("--seed", type=int, default=0,
                        help="scene texture and sensor noise seed (default 0)")
    parser.add_argument("--motion", action="store_true", help="a bright patch drifts between exposures")
    parser.add_argument("--source-ratio", type=float, default=1000.0,
                        help="visible light source radiance / diffuse white (default 1000)")
    parser.add_argument("--response", default="linear", choices=["linear", "gamma", "s-curve"],
                        help="sensor response curve (default linear)")
    parser.add_argument("--faults", default="",
                        help="inject faults, e.g. 'camera:garble@40,stage:disconnect@10x2' "
                             "(kinds: timeout garble partial disconnect again fault; default: none)")


def check_scene_kind(kind: str) -> None:
    """Refuse an unknown ``--scene`` naming every kind (make_scene's list lacks ``natural``,
    which the command line makes itself)."""
    from mehs.calibration.targets import TARGET_KINDS
    from mehs.capture.scene import SCENE_KINDS
    from mehs.errors import InputError

    kinds = (*SCENE_KINDS, "natural", *TARGET_KINDS)
    if kind not in kinds:
        raise InputError(f"unknown --scene {kind!r}; use one of {', '.join(kinds)}")


def build_devices(args, *, port: int = 0, transport: str = "tcp", genicam: bool = False,
                  comm_checksum: bool | None = None):
    """The simulated devices ``args`` describe (not started).

    ``comm_checksum`` starts the stage with its setting ``comm.checksum`` at 1, so that its
    replies carry checksums (default: ``args.comm_checksum``, ``--comm-checksum``).
    """
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simdevice import SimDevices

    lines = getattr(args, "scene_lines", None) or args.size
    samples = getattr(args, "scene_samples", None) or args.size
    check_scene_kind(args.scene)
    if args.scene == "natural":
        from mehs.scenes.natural import make_natural_scene

        scene = make_natural_scene(lines, samples, seed=args.seed, pool=args.pool,
                                   lighting=args.lighting, source_ratio=args.source_ratio,
                                   motion=args.motion)
    else:
        scene = make_scene(args.scene, lines=lines, samples=samples, source_ratio=args.source_ratio,
                           motion=args.motion, seed=args.seed)
    sensor = SensorModel(seed=args.seed, response=args.response)
    if comm_checksum is None:
        comm_checksum = bool(getattr(args, "comm_checksum", False))
    if genicam:
        from mehs.capture.genicam_sim import SimGenicamDevices

        dev = SimGenicamDevices(scene, sensor, faults=args.faults, port=port,
                                pixel_format=getattr(args, "pixel_format", None) or "Mono12",
                                shutter=not getattr(args, "no_shutter", False),
                                comm_checksum=comm_checksum)
        return dev
    return SimDevices(scene, sensor, faults=args.faults, port=port, transport=transport,
                      comm_checksum=comm_checksum)


def configure(parser):
    parser.add_argument("--port", type=int, default=0,
                        help="TCP port of the stage (camera on port+1); 0 picks free ports (default 0)")
    parser.add_argument("--pty", action="store_true", help="serve on pseudo-terminals instead of TCP")
    parser.add_argument("--genicam", action="store_true",
                        help="serve the camera over GigE Vision on 127.0.0.1 (Aravis fake camera; "
                             "camera: aravis://127.0.0.1); the stage stays on TCP")
    parser.add_argument("--pixel-format", choices=["Mono12", "Mono16", "Mono12Packed", "Mono12p"],
                        default="Mono12",
                        help="--genicam: pixel format the camera starts in (default Mono12)")
    parser.add_argument("--no-shutter", action="store_true",
                        help="--genicam: a camera without a shutter feature (darks need --dark-prompt)")
    parser.add_argument("--comm-checksum", action="store_true",
                        help="the stage starts with its setting comm.checksum at 1 and puts a "
                             "checksum on every reply, as a real Zaber stage after "
                             "'/set comm.checksum 1' (for mehs capture --checksum; default: "
                             "replies without checksums, as a new stage)")
    add_scene_arguments(parser)


def run(args):
    import signal
    import sys
    import threading

    from mehs.capture.simdevice import parse_faults
    from mehs.errors import InputError

    if args.genicam:
        from mehs.capture.genicam_sim import split_faults

        if args.pty:
            raise InputError("--genicam serves the camera over GigE Vision; --pty applies to serial devices")
        gv, rest = split_faults(args.faults)
        parse_faults(rest)
    else:
        parse_faults(args.faults)  # fail fast on a bad spec
    dev = build_devices(args, port=args.port, transport="pty" if args.pty else "tcp",
                        genicam=args.genicam)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    with dev:
        print(f"stage: {dev.stage_url}")
        print(f"camera: {dev.camera_url}")
        print(f"lines: {dev.scene_lines}")
        print("ready", flush=True)
        sys.stdout.flush()
        cam = getattr(dev, "camera", None)
        seen = 0
        try:
            while not stop.wait(0.5):
                # what went wrong inside the simulated camera (its fill callback cannot
                # raise into Aravis): said on stderr as it happens
                new = list((getattr(cam, "errors", None) or [])[seen:])
                seen += len(new)   # (the camera's thread may append while this prints)
                for e in new:
                    print(f"mehs sim-device: camera: {e}", file=sys.stderr, flush=True)
        except KeyboardInterrupt:
            pass
    return 0
