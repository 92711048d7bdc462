"""What a scene of the ME HS dataset is built from and keyed by: the build parameters,
a worker's task, the input files whose hashes (with the parameters) make the scene key.

Split from :mod:`mehs.dataset.scene_build` (which re-exports these names), the worker
that builds the scene.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from mehs.dataset.scene_list import SceneSource
from mehs.errors import InputError
from mehs.io.atomic import sha256_file


@dataclass(frozen=True)
class BuildParams:
    """Parameters that change a scene's outputs (they enter the scene key).

    Attributes
    ----------
    method
        Merge estimator name (a key of ``mehs.synthesis.merge.MERGE_METHODS``).
    response
        Path of a response-curve file to use for every scene, or ``None`` to
        recover one per scene.
    ghosts
        Ghost handling passed to ``fuse_bracket`` (``"detect"`` by default).
    seed
        Seed of every random choice (response sampling); also the split seed.
    resample
        Resampling method to 31 bands (``"gaussian"``, ``"linear"``, ``"box"``).
    fwhm
        Target band FWHM in nm for Gaussian/box resampling.
    calibration
        Path of a radiometric calibration (``mehs calibrate``): cubes in
        radiance instead of DN/ms.
    allow_partial
        Fuse a scene whose capture did not finish from its complete exposures.
    ghost_bins
        Adjacent bands summed per term of the merge's χ² ghost statistic
        (``fuse_bracket``'s ``ghost_bins``): ``"auto"`` or a whole number ≥ 1.
    """

    method: str = "poisson"
    response: str | None = None
    ghosts: str = "detect"
    seed: int = 0
    resample: str = "gaussian"
    fwhm: float = 10.0
    calibration: str | None = None
    allow_partial: bool = False
    ghost_bins: int | str = "auto"

    def __post_init__(self):
        # a bad value would otherwise fail every scene one by one and still
        # write a dataset of failed scenes
        from mehs.synthesis.resample import RESAMPLING_METHODS

        if self.resample not in RESAMPLING_METHODS:
            raise InputError(f"unknown resampling method {self.resample!r}; use one of "
                             f"{sorted(RESAMPLING_METHODS)}")
        if not (math.isfinite(self.fwhm) and self.fwhm > 0):
            raise InputError(f"target FWHM must be a positive number of nm, got {self.fwhm}")
        from mehs.synthesis.merge_types import GHOST_BINS_NAME, consistency_bins_value

        # "4" (a command line's) and 4 make the same key
        object.__setattr__(self, "ghost_bins",
                           consistency_bins_value(self.ghost_bins, what=GHOST_BINS_NAME))


@dataclass
class SceneTask:
    """Everything a worker needs to build one scene (picklable)."""

    source: SceneSource
    dataset: str
    params: BuildParams
    previous_key: str | None = None
    response_sha256: str | None = None


def input_files(source: SceneSource) -> dict[str, Path]:
    """Files a scene is built from, by a stable relative name → absolute path.

    Scene folders: ``scene.json`` and every file of the exposure folders that
    ``scene.json`` lists as complete (not ``truth/``). Specim IQ folders: every
    file, prefixed ``<k>/`` for the k-th folder. HS cubes: the header and data file.
    """
    out: dict[str, Path] = {}
    if source.kind == "scene":
        from mehs.capture.scenefolder import read_scene_json

        root = Path(source.paths[0])
        meta = read_scene_json(root)  # checks the structure: a damaged file is a named error
        out["scene.json"] = root / "scene.json"
        for exp in meta["exposures"]:
            if exp.get("status") != "complete":
                continue
            folder = root / exp["folder"]
            if not folder.is_dir():
                raise InputError(f"exposure folder {exp['folder']} is missing", root)
            for f in sorted(folder.rglob("*")):
                if f.is_file():
                    out[f.relative_to(root).as_posix()] = f
    elif source.kind == "specim":
        for k, folder in enumerate(source.paths):
            for f in sorted(Path(folder).rglob("*")):
                if f.is_file():
                    out[f"{k}/{f.relative_to(folder).as_posix()}"] = f
    else:
        from mehs.io.envi import data_file_candidates

        hdr = Path(source.paths[0])
        out[hdr.name] = hdr
        # every file the reader could take as the data (x.bin, x.RAW, ...): one it reads
        # but the key leaves out would let a changed cube reuse its stale outputs
        for data in data_file_candidates(hdr):
            out[data.name] = data
    return out


#: The scene key's ``ghost_bins`` left at "auto" (with the ghost test on), since sessions
#: 35 and 36 changed what "auto" gives: bins for the weighted merges too (35), and for
#: brackets of 4 to 16 exposures (36; 35 had kept one band per bin beyond 3 exposures,
#: mehs.synthesis.merge.AUTO_BINS_MAX_EXPOSURES). A bracket of at most 3 exposures gets
#: what session 35 gave, so its key keeps session 35's rule: only the others rebuild.
AUTO_BINS_RULE = "auto (session 36: bins of 4 for a linear merge of <= 16 exposures)"
AUTO_BINS_RULE_35 = "auto (session 35: bins of 4 for a linear merge of <= 3 exposures)"
AUTO_BINS_RULE_35_EXPOSURES = 3


def bracket_exposures(source: SceneSource) -> int | None:
    """The exposures a scene's bracket merges, from its listing alone (None for a cube):
    a scene folder's complete ones (those :func:`input_files` keys and
    :func:`~mehs.synthesis.bracket.load_bracket` reads), one per Specim IQ folder."""
    if source.kind == "scene":
        from mehs.capture.scenefolder import read_scene_json

        meta = read_scene_json(Path(source.paths[0]))
        return sum(1 for exp in meta["exposures"] if exp.get("status") == "complete")
    if source.kind == "specim":
        return len(source.paths)
    return None


def _params_for_key(task: SceneTask) -> dict[str, Any]:
    p = asdict(task.params)
    p["response"] = task.response_sha256  # the curve's content, not where it lives
    if p.get("calibration"):
        p["calibration"] = sha256_file(p["calibration"])
    if not p.get("allow_partial"):
        p.pop("allow_partial", None)  # keys of complete scenes stay what they were
    if p.get("ghost_bins") == "auto":
        if p.get("ghosts") != "off":
            # the ghost masks of a weighted merge's scenes (session 35) and of brackets of
            # more than 3 exposures (36, now binned) changed: such scenes rebuild once
            n = bracket_exposures(task.source)
            p["ghost_bins"] = (AUTO_BINS_RULE_35 if n is not None
                               and n <= AUTO_BINS_RULE_35_EXPOSURES else AUTO_BINS_RULE)
        else:
            p.pop("ghost_bins", None)     # no statistic: keys as before the option existed
    if task.source.kind == "hs":
        for k in ("method", "response", "ghosts", "ghost_bins"):
            p.pop(k, None)
    return p
