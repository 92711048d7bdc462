"""Writing a fusion result (:func:`mehs.synthesis.fuse.fuse_bracket`) into a folder."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mehs.errors import InputError

if TYPE_CHECKING:
    from mehs.synthesis.fuse import FusionResult

#: The file written last: its presence means the folder holds one complete fusion.
SUMMARY_NAME = "summary.json"


def write_fusion(result: "FusionResult", out_dir: str | Path) -> dict[str, Path]:
    """Write a fusion result into ``out_dir``.

    Files: ``radiance.hdr`` + ``radiance.dat`` (ENVI float32, BIL, with
    wavelengths), ``mask.png`` (uint8, dataset mask bits), ``confidence.exr``
    (float32 single channel ``Y``), ``response.json`` (the curve, reloadable
    with ``--response``), ``summary.json``. Every file is written atomically.

    ``summary.json`` is the commit point of the set: an earlier one is removed before
    the first new file is written, and the new one, written last, records the SHA-256 of
    every other file (``sha256``). A run killed at any instant (SIGKILL, power loss)
    therefore never leaves a summary beside files of another run, or beside files it
    does not describe; a folder without ``summary.json`` holds an unfinished fusion,
    which the next ``mehs fuse`` replaces.
    """
    from mehs.io.atomic import make_output_dir
    from mehs.io.lock import OutputLock

    out = make_output_dir(out_dir)
    with OutputLock(out, what="mehs fuse"):   # a second run into this --out is refused
        return _write_fusion_files(result, out)


def _write_fusion_files(result: "FusionResult", out: Path) -> dict[str, Path]:
    from mehs.io.atomic import atomic_path, sha256_file, unlink_durable, write_json_atomic
    from mehs.io.envi import write_envi
    from mehs.io.exr import write_exr_gray

    # the old commit point goes first (and durably): from here until the new summary is
    # in place the folder says "unfinished", never "complete" with a mix of two runs
    unlink_durable(out / SUMMARY_NAME)
    paths: dict[str, Path] = {}
    digests: dict[str, str] = {}     # the cube's, hashed as written (no second read)
    paths["radiance"] = write_envi(out / "radiance.hdr", result.radiance, dtype=np.float32,
                                   interleave="bil", data_ext=".dat", overwrite=True,
                                   sha256=digests)
    import cv2

    with atomic_path(out / "mask.png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(result.mask)):
            raise InputError("could not write PNG", out / "mask.png")
    paths["mask"] = out / "mask.png"
    paths["confidence"] = write_exr_gray(out / "confidence.exr",
                                         np.ascontiguousarray(result.confidence), half=False)
    paths["response"] = result.response.save(out / "response.json")
    summary = dict(result.summary)
    summary["files"] = {k: p.name for k, p in paths.items()}
    digests.update({p.name: sha256_file(p) for k, p in paths.items() if k != "radiance"})
    summary["sha256"] = dict(sorted(digests.items()))
    paths["summary"] = write_json_atomic(out / SUMMARY_NAME, summary)
    return paths
