"""Simulated brackets without any transport: scene × sensor → raw cubes + references.

The simulated *world* seen by the pushbroom camera is a strip of lines:
scene lines ``0 … lines−1``, a gap of :data:`WHITE_GAP_LINES` black lines, then a
diffuse white reference tile :data:`WHITE_TILE_LINES` lines long. Dark
references are shutter-closed lines ``0 … dark_lines−1``; white references are
the tile's lines. The noise of every line is keyed by
``(sensor.seed, exposure seed, line index, shutter)``, with the exposure seed
derived from the integration time (:func:`mehs.capture.sensor.exposure_seed_for`),
so :func:`simulate_bracket` (``seed=0``) and a capture through the simulated
devices produce byte-identical cubes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mehs.capture.scene import Scene
from mehs.capture.sensor import SensorModel, exposure_seed_for
from mehs.errors import InputError

#: Black lines between the scene and the white tile.
WHITE_GAP_LINES = 4
#: Length (lines) of the white reference tile.
WHITE_TILE_LINES = 16


def white_tile_first_line(scene_lines: int) -> int:
    """World line index of the white tile's first line."""
    return int(scene_lines) + WHITE_GAP_LINES


def world_radiance_line(scene: Scene, line_index: int, exposure_index: float = 0) -> np.ndarray:
    """float32 ``(samples, bands)`` radiance at world line ``line_index`` (scene, gap, tile or black)."""
    lines, samples, bands = scene.radiance.shape
    if 0 <= line_index < lines:
        return scene.radiance_at(exposure_index, rows=slice(line_index, line_index + 1))[0]
    w0 = white_tile_first_line(lines)
    if w0 <= line_index < w0 + WHITE_TILE_LINES and scene.white_radiance is not None:
        return np.broadcast_to(scene.white_radiance.astype(np.float32), (samples, bands))
    return np.zeros((samples, bands), dtype=np.float32)


def motion_phase(integration_time_ms: float) -> float:
    """Exposure index the simulated camera assigns to an integration time (for scene motion).

    A device does not know which exposure of a bracket it is taking, so the
    simulated world moves with the integration time: one exposure index per
    factor 4 in time (``log4(t / 1 ms)``), matching a ×4 bracket.
    """
    return float(np.log(float(integration_time_ms)) / np.log(4.0))


@dataclass
class SimulatedBracket:
    """A simulated bracket (shortest exposure first).

    Attributes
    ----------
    exposures
        uint16 ``(lines, samples, bands)`` raw DN per exposure.
    darks
        float32 ``(samples, bands)`` mean of ``dark_lines`` shutter-closed lines at each time.
    white
        float32 ``(samples, bands)`` white reference (mean of the tile lines) at the
        shortest time, or ``None``; ``whites`` holds it for every time.
    times_ms
        float64 ``(n,)`` integration times, ascending.
    wavelengths, fwhm
        Band centres / widths (nm).
    truth
        float32 ``(lines, samples, bands)`` scene radiance of exposure 0 (relative units).
    truth_dn_per_ms
        float64 ``(bands,)``: linear DN per ms per unit radiance, so dark-subtracted,
        linearised ``DN / t ≈ truth · truth_dn_per_ms``.
    """

    exposures: list[np.ndarray]
    darks: list[np.ndarray]
    white: np.ndarray | None
    times_ms: np.ndarray
    wavelengths: np.ndarray
    truth: np.ndarray
    scene: Scene
    sensor: SensorModel
    fwhm: np.ndarray | None = None
    whites: list[np.ndarray] | None = None
    truth_dn_per_ms: np.ndarray | None = None
    seed: int = 0
    dark_lines: int = 16
    saturation_fractions: list[float] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    #: uint16 ``(dark_lines, samples, bands)`` per exposure: the lines ``darks`` averages
    dark_frames: list[np.ndarray] | None = None
    #: uint16 ``(WHITE_TILE_LINES, samples, bands)`` per exposure: the lines ``whites`` averages
    white_frames: list[np.ndarray] | None = None


def _check_times(times_ms: Sequence[float]) -> np.ndarray:
    t = np.asarray(times_ms, dtype=np.float64).reshape(-1)
    if t.size == 0 or not np.all(np.isfinite(t) & (t > 0)):
        raise InputError(f"integration times must be positive and finite, got {t.tolist()}")
    if np.any(np.diff(t) <= 0):
        raise InputError(f"integration times must be strictly ascending, got {t.tolist()}")
    return t


def dark_lines_at(sensor: SensorModel, samples: int, bands: int, t: float, *,
                  dark_lines: int = 16, exposure_seed: int, wavelengths=None) -> np.ndarray:
    """uint16 ``(dark_lines, samples, bands)``: shutter-closed lines at ``t``."""
    zeros = np.zeros((samples, bands), dtype=np.float32)
    return np.stack([sensor.expose_line(zeros, t, exposure_seed=exposure_seed, line_index=j,
                                        shutter_open=False, wavelengths=wavelengths)
                     for j in range(dark_lines)])


def dark_reference(sensor: SensorModel, samples: int, bands: int, t: float, *, dark_lines: int = 16,
                   exposure_seed: int, wavelengths=None) -> np.ndarray:
    """float32 ``(samples, bands)``: mean of ``dark_lines`` shutter-closed lines at ``t``."""
    return _line_mean(dark_lines_at(sensor, samples, bands, t, dark_lines=dark_lines,
                                    exposure_seed=exposure_seed, wavelengths=wavelengths))


def _line_mean(stack: np.ndarray) -> np.ndarray:
    return stack.mean(axis=0, dtype=np.float64).astype(np.float32)


def simulate_bracket(scene: Scene, sensor: SensorModel, times_ms: Sequence[float], *, seed: int = 0,
                     dark_lines: int = 16, white: bool = True) -> SimulatedBracket:
    """Expose ``scene`` at each of ``times_ms`` (ascending) with ``sensor``.

    Parameters
    ----------
    seed
        Mixed into every exposure seed; ``0`` reproduces the simulated devices
        byte for byte (their noise depends on the sensor seed only).
    dark_lines
        Shutter-closed lines averaged into each dark reference.
    white
        Also expose the white tile (:data:`WHITE_TILE_LINES` lines) at each time.

    Returns
    -------
    SimulatedBracket
    """
    t = _check_times(times_ms)
    if int(seed) < 0:
        raise InputError(f"seed must be >= 0, got {seed}")
    if dark_lines < 1:
        raise InputError(f"dark_lines must be >= 1, got {dark_lines}")
    lines, samples, bands = scene.radiance.shape
    wl = scene.wavelengths
    exposures, darks, whites, sat = [], [], [], []
    dark_frames, white_frames = [], []
    for k, tk in enumerate(t):
        es = exposure_seed_for(tk) + (int(seed) << 64)
        rad = scene.radiance_at(k)
        cube = sensor.expose(rad, tk, exposure_seed=es, wavelengths=wl)
        exposures.append(cube)
        sat.append(float(np.count_nonzero(cube >= sensor.saturation_dn) / cube.size))
        dstack = dark_lines_at(sensor, samples, bands, tk, dark_lines=dark_lines,
                               exposure_seed=es, wavelengths=wl)
        dark_frames.append(dstack)
        darks.append(_line_mean(dstack))
        if white and scene.white_radiance is not None:
            w0 = white_tile_first_line(lines)
            tile = np.broadcast_to(scene.white_radiance.astype(np.float32),
                                   (WHITE_TILE_LINES, samples, bands))
            wc = sensor.expose(tile, tk, exposure_seed=es, line_offset=w0, wavelengths=wl)
            white_frames.append(wc)
            whites.append(_line_mean(wc))
    return SimulatedBracket(
        exposures=exposures, darks=darks, white=whites[0] if whites else None, times_ms=t,
        wavelengths=np.asarray(wl, dtype=np.float64),
        fwhm=None if scene.fwhm is None else np.asarray(scene.fwhm, dtype=np.float64),
        truth=scene.radiance, scene=scene, sensor=sensor, whites=whites or None,
        truth_dn_per_ms=sensor.signal_scale(bands, wl), seed=int(seed), dark_lines=dark_lines,
        saturation_fractions=sat, info=dict(scene.info), dark_frames=dark_frames,
        white_frames=white_frames or None)


def write_simulated_scene(sim: SimulatedBracket, scene_dir: str | Path, *,
                          scene_id: str | None = None, overwrite: bool = False) -> Path:
    """Write ``sim`` as a scene folder (format ``mehs-scene/1``) including ``truth/radiance.hdr``.

    Layout: ``scene.json``, ``exposures/<k>_<t>ms/`` Specim IQ folders (raw,
    DARKREF and WHITEREF at that time) and the ground truth as ENVI float32;
    with scene motion also ``truth/moved_mask.png`` (uint8, 255 = the radiance
    differs between exposures; key ``truth_moved_mask``).
    The truth header carries ``mehs dn per ms per radiance`` (per band, see
    :attr:`SimulatedBracket.truth_dn_per_ms`). Raw captures are never
    overwritten: an existing scene folder raises unless ``overwrite``.
    """
    from mehs.capture import scenefolder as sf

    scene_dir = Path(scene_dir)
    if (scene_dir / sf.SCENE_JSON).exists() and not overwrite:
        raise InputError("scene folder already exists; refusing to overwrite a raw capture",
                         scene_dir)
    scene_id = scene_id or scene_dir.name
    lines, samples, bands = sim.truth.shape
    doc = sf.new_scene_doc(scene_id, sim.wavelengths, seed=sim.seed,
                           device={"kind": "simulated (no transport)", "scene": sim.info,
                                   "sensor": sf.sensor_info(sim.sensor)})
    sf.write_scene_json(scene_dir, doc)
    for k, tk in enumerate(sim.times_ms):
        # the lines themselves when known: the device stores them, a reader averages them
        white = (sim.white_frames[k] if sim.white_frames else
                 sim.whites[k] if sim.whites else None)
        dark = sim.dark_frames[k] if sim.dark_frames else sim.darks[k]
        rec = sf.write_exposure(
            scene_dir, k, float(tk), sim.exposures[k], dark, white,
            wavelengths=sim.wavelengths, fwhm=sim.fwhm, requested_ms=float(tk),
            extra={"frame_rate_hz": sf.frame_rate_hz(float(tk)), "temperature_c": 25.0,
                   "saturation_fraction": sim.saturation_fractions[k],
                   "stage": {"start_position": 0, "end_position": (lines - 1) * sf.DEFAULT_PITCH,
                             "warnings": []}},
            overwrite=overwrite)
        doc["exposures"].append(rec)
        sf.write_scene_json(scene_dir, doc)
    write_truth(scene_dir, doc, sim.truth, sim.wavelengths, fwhm=sim.fwhm,
                dn_per_ms=sim.truth_dn_per_ms, overwrite=overwrite)
    if sim.scene.moving:
        write_moved_mask(scene_dir, doc, sim.scene.moved_mask(len(sim.times_ms)),
                         overwrite=overwrite)
    sf.write_scene_json(scene_dir, doc)
    return scene_dir


def write_moved_mask(scene_dir: str | Path, doc: dict, moved: np.ndarray, *,
                     overwrite: bool = False) -> Path:
    """Write ``truth/moved_mask.png`` (uint8, 255 where ``moved``: the radiance differs
    between the exposures of a moving scene) and record it in ``doc``
    (``truth_moved_mask``, ``moved_mask_pixels``; rewritten atomically): the truth is the
    first exposure's radiance, so a comparison must leave these pixels out."""
    import cv2

    from mehs.capture import scenefolder as sf
    from mehs.io.atomic import atomic_path

    scene_dir = Path(scene_dir)
    path = scene_dir / "truth" / "moved_mask.png"
    with atomic_path(path, overwrite=overwrite) as tmp:
        if not cv2.imwrite(str(tmp), (moved * 255).astype(np.uint8)):
            raise InputError("could not write the moved-pixel mask", tmp)
    doc["truth_moved_mask"] = "truth/moved_mask.png"
    doc["moved_mask_pixels"] = int(moved.sum())
    sf.write_scene_json(scene_dir, doc)
    return path


def write_truth(scene_dir: str | Path, doc: dict, radiance: np.ndarray, wavelengths, *, fwhm=None,
                dn_per_ms: np.ndarray | None = None, overwrite: bool = False) -> Path:
    """Write ``truth/radiance.hdr`` (ENVI float32) into a scene folder and record it in ``doc``.

    ``doc`` (the scene.json document) gets ``truth`` and
    ``truth_dn_per_ms_per_radiance`` and is rewritten atomically.
    """
    from mehs.capture import scenefolder as sf
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi

    scene_dir = Path(scene_dir)
    truth = SpectralCube(np.asarray(radiance, dtype=np.float32), wavelengths, fwhm=fwhm,
                         units="relative radiance")
    extra = {}
    if dn_per_ms is not None:
        extra["mehs dn per ms per radiance"] = [float(f"{v:.6g}") for v in dn_per_ms]
        doc["truth_dn_per_ms_per_radiance"] = [float(v) for v in dn_per_ms]
    hdr = scene_dir / "truth" / "radiance.hdr"
    write_envi(hdr, truth, dtype=np.float32, overwrite=overwrite, extra_header=extra)
    doc["truth"] = "truth/radiance.hdr"
    sf.write_scene_json(scene_dir, doc)
    return hdr
