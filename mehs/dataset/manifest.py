"""The dataset manifest (``manifest.json``) and its CSV index (``index.csv``).

The manifest is the single source of truth of a dataset folder: a scene is part
of the dataset only once its entry is in the manifest, and the manifest is
rewritten atomically (temp + rename) after every scene, so a crash never leaves
a half-built scene listed. Entries are kept sorted by scene id and every
sub-dictionary is key-sorted, so two builds of the same inputs give the same
bytes except for the documented volatile subtree ``scenes[].provenance.run``
(wall-clock start/finish and stage timings), see :data:`VOLATILE_FIELDS`.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import io
import json
from pathlib import Path
from typing import Any, Iterable

from mehs.errors import FormatError
from mehs.io.atomic import write_json_atomic, write_text_atomic

FORMAT = "mehs-dataset/1"
MANIFEST_NAME = "manifest.json"
INDEX_NAME = "index.csv"

#: The only fields whose values change between two builds of the same inputs.
VOLATILE_FIELDS = ("scenes[].provenance.run",)

#: Columns of ``index.csv``, one row per scene, in manifest order.
INDEX_COLUMNS = ("id", "status", "split", "reasons", "dynamic_range_stops",
                 "saturated_fraction", "ghost_fraction", "invalid_fraction",
                 "exposure_ratios", "hs", "hdr_rgb", "ldr_rgb", "mask", "key")


def new_manifest(*, software_version: str, wavelengths: Iterable[float],
                 rgb: dict[str, str]) -> dict[str, Any]:
    """An empty manifest for a dataset with band centres ``wavelengths`` (nm)."""
    return {"format": FORMAT, "software_version": software_version,
            "wavelengths": [float(w) for w in wavelengths], "rgb": dict(rgb),
            "scenes": [], "splits": {"train": [], "val": [], "test": []}}


def read_manifest(dataset: str | Path) -> dict[str, Any]:
    """Read ``DATASET/manifest.json`` (or the file itself) and check its format tag.

    Raises
    ------
    FormatError
        When the file is not JSON or not a ``mehs-dataset/1`` manifest.
    """
    path = Path(dataset)
    if path.is_dir():
        path = path / MANIFEST_NAME
    try:
        with open(path, encoding="utf-8") as fh:
            manifest = json.load(fh)
    except FileNotFoundError:
        raise FormatError("no dataset manifest here", path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"manifest is not valid JSON ({exc})", path) from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise FormatError(f"not a {FORMAT} manifest (format {got!r})", path)
    if not isinstance(manifest.get("scenes"), list):
        raise FormatError("manifest has no 'scenes' list", path)
    # a hand-edited or damaged entry must fail here, by name, not as a
    # TypeError/KeyError in whichever command reads it next
    from mehs.dataset.scene_list import SCENE_ID_RE

    for i, s in enumerate(manifest["scenes"]):
        if not isinstance(s, dict) or not isinstance(s.get("id"), str) or not s["id"]:
            raise FormatError(f"scene entry #{i + 1} is not an object with an 'id'", path)
        if not SCENE_ID_RE.match(s["id"]):
            # ids name folders that builds replace and remove: '../x' would reach outside
            raise FormatError(f"scene entry #{i + 1}: id {s['id']!r} is not a folder name "
                              "(letters, digits, '.', '_', '-'; not starting with '.' or '-')",
                              path)
        for key in ("files", "sha256"):  # without them nothing of the scene can be verified
            if not isinstance(s.get(key), dict):
                what = "is missing" if key not in s else "must be an object"
                raise FormatError(f"scene {s['id']!r}: '{key}' {what} (damaged entry; "
                                  "rebuild the scene with 'mehs build ... --force')", path)
        for name, rel in s["files"].items():
            # a path that leaves the dataset; a missing or non-path entry is a damaged scene,
            # which the build names and rebuilds (scene_build), not a hostile manifest
            if isinstance(rel, str) and rel and (Path(rel).is_absolute() or ".." in Path(rel).parts):
                raise FormatError(f"scene {s['id']!r}: file {name!r} = {rel!r} is not a path "
                                  "inside the dataset (damaged or hand-edited entry)", path)
    splits = manifest.get("splits", {})
    if not isinstance(splits, dict) or not all(isinstance(v, list) for v in splits.values()):
        raise FormatError("'splits' must map split names to lists of scene ids", path)
    return manifest


def scene_map(manifest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Scene entries of ``manifest`` by id."""
    return {s["id"]: s for s in manifest["scenes"]}


def write_manifest(dataset: str | Path, manifest: dict[str, Any]) -> Path:
    """Write ``manifest.json`` and ``index.csv`` atomically; scenes sorted by id.

    The index is written first so that the manifest (the commit point) is never
    ahead of it by more than the scene being committed.
    """
    dataset = Path(dataset)
    manifest["scenes"] = sorted(manifest["scenes"], key=lambda s: s["id"])
    write_text_atomic(dataset / INDEX_NAME, index_csv(manifest))
    return write_json_atomic(dataset / MANIFEST_NAME, manifest)


def index_csv(manifest: dict[str, Any]) -> str:
    """The CSV index text: :data:`INDEX_COLUMNS`, one row per scene."""
    split_of = {sid: name for name, ids in manifest.get("splits", {}).items() for sid in ids}
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(INDEX_COLUMNS)
    for s in sorted(manifest["scenes"], key=lambda s: s["id"]):
        q = s.get("quality") or {}
        files = s.get("files") or {}
        ratios = q.get("exposure_ratios")
        writer.writerow([
            s["id"], s["status"], split_of.get(s["id"], ""), "; ".join(s.get("reasons", [])),
            _fmt(q.get("dynamic_range_stops")), _fmt(q.get("saturated_fraction")),
            _fmt(q.get("ghost_fraction")), _fmt(q.get("invalid_fraction")),
            "" if not ratios else " ".join(_fmt(r) for r in ratios),
            files.get("hs", ""), files.get("hdr_rgb", ""), files.get("ldr_rgb", ""),
            files.get("mask", ""), s.get("key") or ""])
    return buf.getvalue()


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def strip_volatile(manifest: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of ``manifest`` without the :data:`VOLATILE_FIELDS`."""
    out = copy.deepcopy(manifest)
    for scene in out.get("scenes", []):
        scene.get("provenance", {}).pop("run", None)
    return out


def scene_key(input_sha256: dict[str, str], params: dict[str, Any],
              software_version: str) -> str:
    """Hex SHA-256 identifying one scene build: inputs' hashes + parameters + version.

    A scene whose stored key equals the key of a new request is not rebuilt.
    """
    blob = json.dumps({"inputs": input_sha256, "params": params,
                       "software_version": software_version},
                      sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()
