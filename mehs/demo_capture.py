"""Captures of ``mehs demo``: scenes, the response ladder and the calibration sphere.

Each goes through the real serial drivers (:class:`~mehs.capture.zaber.ZaberStage`,
:class:`~mehs.capture.camera.LineCamera`) talking to the simulated devices over
loopback TCP (:class:`mehs.capture.simdevice.SimDevices`), exactly as a lab's
capture would; :mod:`mehs.demo` runs the stages after them.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

from mehs.demo_scenes import DemoScene
from mehs.errors import InputError

#: Auto-exposure of the demo scenes: the longest exposure brings the darkest decile to
#: 30× the dark noise (the default 10× leaves the darkest quarter of these dusk scenes
#: ~1.8° from the truth, shot-noise limited).
DEMO_AUTO_EXPOSURE = {"target_snr": 30.0, "n": 4}


def _scene_seed(seed: int, index: int) -> int:
    return int(seed) * 1000 + index


def capture_demo_scene(spec: DemoScene, folder: Path, *, size: int, seed: int, index: int,
                       progress: bool = False, log: Callable[[str], None] = print,
                       auto_options: dict | None = None, pool: str = "all") -> dict[str, Any]:
    """Capture (or resume, or reuse) one demo scene through the serial drivers; returns scene.json.

    A folder whose ``scene.json`` was made for other scene parameters is an
    error (the demo never overwrites a capture).
    """
    from mehs.capture import scenefolder as sf
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.errors import DeviceError

    s_seed = _scene_seed(seed, index)
    demo_info = {**asdict(spec), "size": size, "seed": s_seed}
    if spec.kind == "natural":
        demo_info["pool"] = pool
    resume = False
    if (folder / sf.SCENE_JSON).is_file():
        doc = sf.read_scene_json(folder)
        if doc.get("device", {}).get("demo") != demo_info:
            raise InputError("this capture was made with other demo parameters; use another "
                             "--out or --force (which deletes the demo's captures)", folder)
        done = all(e.get("status") == "complete" for e in doc.get("exposures", [])) and \
            len(doc.get("exposures", [])) == len(doc.get("plan", {}).get("times_ms", [None]))
        if done and doc.get("truth"):
            log(f"  {spec.scene_id}: already captured, kept")
            return doc
        resume = True
    if spec.kind == "natural":
        from mehs.scenes.natural import make_natural_scene

        scene = make_natural_scene(size, size, seed=s_seed, pool=pool, lighting=spec.lighting,
                                   source_ratio=spec.source_ratio, motion=spec.motion)
    else:
        scene = make_scene(spec.kind, size, size, illuminant=spec.illuminant,
                           light_source=spec.light_source, source_ratio=spec.source_ratio,
                           motion=spec.motion, seed=s_seed)
    sensor = SensorModel(seed=s_seed)
    try:
        return _capture(spec, folder, scene, sensor, resume=resume, seed=s_seed,
                        demo_info=demo_info, progress=progress, log=log,
                        auto_options=DEMO_AUTO_EXPOSURE if auto_options is None else auto_options)
    except DeviceError as exc:
        raise DeviceError(f"{exc.problem} — completed exposures are kept; run the same "
                          f"'mehs demo' again to resume", exc.path) from exc


def _capture(spec: DemoScene, folder: Path, scene, sensor, *, resume: bool, seed: int,
             demo_info: dict, progress: bool, log: Callable[[str], None],
             auto_options: dict | None = None) -> dict[str, Any]:
    from mehs.capture.camera import LineCamera
    from mehs.capture.session import capture_scene
    from mehs.capture.simdevice import SimDevices
    from mehs.capture.simulate import motion_phase, write_truth
    from mehs.capture.zaber import ZaberStage

    s_seed = seed
    with SimDevices(scene, sensor) as dev:
        stage = ZaberStage.open(dev.stage_url, timeout=2.0)
        try:
            camera = LineCamera.open(dev.camera_url, timeout=2.0)
            try:
                doc = capture_scene(stage, camera, folder, auto=not resume, resume=resume,
                                    lines=dev.scene_lines, scene_id=spec.scene_id, seed=s_seed,
                                    progress=progress, auto_options=auto_options,
                                    device_info={"simulated": True, "scene": scene.info,
                                                 "demo": demo_info},
                                    log=lambda m: log(f"  {spec.scene_id}: {m}"))
            finally:
                camera.close()
        finally:
            stage.close()
        if doc.get("truth") is None:
            t0 = doc["exposures"][0]["integration_time_ms"]
            phase = motion_phase(t0) if scene.moving else 0
            write_truth(folder, doc, scene.radiance_at(phase), scene.wavelengths, fwhm=scene.fwhm,
                        dn_per_ms=sensor.signal_scale(scene.wavelengths.size, scene.wavelengths))
            if scene.moving:
                # the truth is the first exposure's radiance: where later ones differ
                # there is no single truth to compare with
                from mehs.capture.simulate import write_moved_mask

                phases = [motion_phase(e["integration_time_ms"]) for e in doc["exposures"]]
                write_moved_mask(folder, doc, scene.moved_between(phases))
    return doc


def demo_response_ladder(folder: Path, curve_path: Path, *, size: int, seed: int,
                         progress: bool = False, log: Callable[[str], None] = print) -> Path:
    """Capture a response ladder once (a static grey ramp, ≥ 5 exposures ×4 apart) and save its curve.

    A 3-exposure HDR bracket ×30–×150 apart cannot tell a linear sensor from a
    non-linear one (:mod:`mehs.synthesis.response_check`); the ladder can, and
    every scene is then fused with its curve (``--response curve.json``).
    """
    import warnings

    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import ResponseUndeterminedWarning, fuse_bracket

    spec = DemoScene("response_ladder", "ramp", "D65", None, 0.0, False,
                     "grey ramp over 4 decades, a x4 exposure ladder")
    capture_demo_scene(spec, folder, size=size, seed=seed, index=98, progress=progress, log=log,
                       auto_options={"n": 5, "max_step": 4.0})
    if curve_path.is_file():     # made from this very capture (--force clears both)
        return curve_path
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResponseUndeterminedWarning)
        res = fuse_bracket(load_bracket(folder), response="auto", ghosts="off")
    res.response.parameters["ladder"] = str(folder)
    res.response.save(curve_path)
    return curve_path


def calibrate_demo_camera(folder: Path, cal_path: Path, *, size: int, seed: int,
                          progress: bool = False, log: Callable[[str], None] = print) -> Path:
    """Capture the simulated integrating sphere and calibrate the camera (absolute radiance).

    As a lab would: the sphere fills the view, its certificate (CSV, 5 nm,
    W·sr⁻¹·m⁻²·nm⁻¹) comes with it, :func:`mehs.calibration.calibrate_source_absolute`
    turns the fused capture into per-column responsivity. Reused when present.
    """
    from mehs.calibration import Calibration, calibrate_source_absolute, load_spectrum
    from mehs.calibration.targets import sphere_certificate
    from mehs.synthesis.bracket import load_bracket

    spec = DemoScene("calibration_sphere", "sphere", None, None, 0.0, False,
                     "integrating sphere (QTH, 3000 K) with its certificate")
    capture_demo_scene(spec, folder, size=size, seed=seed, index=99, progress=progress, log=log)
    cert = folder / "truth" / "source_radiance.csv"
    if not cert.is_file():
        sphere_certificate(cert)
    if cal_path.is_file():      # made from this very capture (--force clears both)
        Calibration.load(cal_path)   # a damaged file is a named error here, not in the build
        return cal_path
    cal = calibrate_source_absolute(load_bracket(folder), load_spectrum(cert, what="sphere certificate"))
    cal.save(cal_path)
    return cal_path
