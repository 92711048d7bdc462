"""How close a dataset's HS cubes are to the simulator's true radiance (same bands, same pixels).

Independent truth: ``truth/radiance.hdr`` written by the simulator beside each
capture (the radiance the simulated camera looked at, W·sr⁻¹·m⁻²·nm⁻¹). The
truth is resampled to the dataset's 31 bands by the same band operation as the
data (the build's ``resample`` / ``fwhm``, default Gaussian 10 nm), the
dataset's half-float power-of-two scale is undone, and pixels masked by the
builder (saturated in every exposure, ghosts, no signal) are left out — they
hold bounds, not estimates.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np


def radiance_accuracy(hs: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None, *,
                      absolute: bool = True) -> dict[str, Any]:
    """Median spectral angle (°) and relative error of ``hs`` against ``truth``.

    Parameters
    ----------
    hs, truth
        float ``(lines, samples, bands)`` on the same bands.
    mask
        uint8 ``(lines, samples)``; non-zero pixels are excluded.
    absolute
        Compare levels as they are (absolute calibration); ``False`` removes
        one global scale first (relative radiance).

    Returns
    -------
    dict
        ``sam_median_deg``, ``rel_error_median``, ``rel_error_p95``, ``scale``
        (median hs/truth), ``pixels``.
    """
    hs = np.asarray(hs, dtype=np.float64)
    tr = np.asarray(truth, dtype=np.float64)
    ok = np.ones(hs.shape[:2], dtype=bool) if mask is None else (np.asarray(mask) == 0)
    ok &= (np.linalg.norm(tr, axis=2) > 0) & np.all(np.isfinite(hs), axis=2)
    a, b = hs[ok], tr[ok]
    cos = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-300)
    sam = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    pos = b > 0
    scale = float(np.median(a[pos] / b[pos])) if pos.any() else float("nan")
    k = 1.0 if absolute else scale
    rel = np.abs(a[pos] / k - b[pos]) / b[pos]
    return {"sam_median_deg": float(np.median(sam)), "rel_error_median": float(np.median(rel)),
            "rel_error_p95": float(np.percentile(rel, 95)), "scale": scale,
            "pixels": int(ok.sum()), "absolute": bool(absolute)}


def dataset_truth_accuracy(dataset: str | Path, captures: dict[str, str | Path]) -> dict[str, dict]:
    """:func:`radiance_accuracy` of every built scene of ``dataset`` that has a simulator truth.

    ``captures`` maps scene ids to their capture folders (holding ``scene.json``
    with a ``truth`` entry). Scenes without truth are skipped.
    """
    import cv2

    from mehs.dataset.build import to_31_bands
    from mehs.dataset.manifest import read_manifest
    from mehs.io.envi import read_envi

    dataset = Path(dataset)
    man = read_manifest(dataset)
    unit = man.get("radiance_unit") or ""
    out: dict[str, dict] = {}
    for s in man["scenes"]:
        cap = captures.get(s["id"])
        files = s.get("files") or {}
        if cap is None or not files.get("hs"):
            continue
        doc = json.loads((Path(cap) / "scene.json").read_text(encoding="utf-8"))
        if not doc.get("truth"):
            continue
        # the truth goes through the band operation the scene was built with
        params = (s.get("provenance") or {}).get("params") or {}
        truth = to_31_bands(read_envi(Path(cap) / doc["truth"]),
                            method=params.get("resample") or "gaussian",
                            fwhm=float(params.get("fwhm") or 10.0))
        hs = np.asarray(read_envi(dataset / files["hs"]).data, dtype=np.float64)
        hs /= float((s.get("quality") or {}).get("radiance_scale") or 1.0)
        mask = cv2.imread(str(dataset / files["mask"]), cv2.IMREAD_UNCHANGED) if files.get("mask") else None
        if doc.get("truth_moved_mask"):
            # a moving scene's truth is its first exposure: pixels that changed later have
            # no single truth (the ghost test misses some: a few electrons in the shortest)
            from mehs.errors import FormatError

            moved = cv2.imread(str(Path(cap) / doc["truth_moved_mask"]), cv2.IMREAD_UNCHANGED)
            if moved is None or moved.shape != hs.shape[:2]:
                raise FormatError("moved-pixel mask unreadable or not the scene's size "
                                  f"{hs.shape[:2]}", Path(cap) / doc["truth_moved_mask"])
            mask = moved if mask is None else np.where(moved > 0, 255, mask).astype(np.uint8)
        out[s["id"]] = radiance_accuracy(hs, np.asarray(truth.data), mask,
                                         absolute=unit == "W sr-1 m-2 nm-1")
    return out
