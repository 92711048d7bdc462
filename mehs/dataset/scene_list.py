"""What to build: scene folders, scene lists (CSV/TOML) and HS cubes → :class:`SceneSource`.

Accepted inputs of ``mehs build``:

- a **scene folder** (dataset format 2: ``<scene>/scene.json`` + ``exposures/``),
  its id taken from ``scene.json``'s ``scene_id``;
- a folder whose sub-folders are scene folders (all of them, sorted by name);
- a **CSV scene list** with the header ``scene_id,folder_short,folder_mid,folder_long``:
  three Specim IQ capture folders per scene, shortest integration time first
  (relative paths are relative to the CSV file's folder; blank lines and lines
  starting with ``#`` are ignored; extra columns are ignored);
- a **TOML scene list**: ``[[scene]]`` tables with ``id = "..."`` and
  ``folders = ["short", "mid", "long"]`` (two or more folders, shortest first).

``mehs build --from-hs`` takes ENVI cubes instead (``.hdr`` files, or folders
searched for ``*.hdr``); their id is the file stem.
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path

from mehs.errors import InputError

SCENE_LIST_COLUMNS = ("scene_id", "folder_short", "folder_mid", "folder_long")
#: what a scene id may be: a folder name of its own (manifest ids are checked against it too)
SCENE_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*\Z")   # \Z: no trailing newline


@dataclass(frozen=True)
class SceneSource:
    """One scene to build.

    Attributes
    ----------
    scene_id
        Dataset id (folder name under ``scenes/``): letters, digits, ``._-``.
    kind
        ``"scene"`` (a scene folder), ``"specim"`` (Specim IQ folders, one per
        exposure, shortest first) or ``"hs"`` (an existing ENVI HS cube).
    paths
        Absolute paths: the scene folder, the Specim IQ folders, or the cube's ``.hdr``.
    """

    scene_id: str
    kind: str
    paths: tuple[str, ...]

    @property
    def load_arg(self) -> str | list[str]:
        """What :func:`mehs.synthesis.bracket.load_bracket` takes for this scene."""
        return self.paths[0] if self.kind != "specim" else list(self.paths)


def check_scene_id(scene_id: str, source: str | Path | None = None) -> str:
    """Return ``scene_id`` if it is usable as a folder name, else raise InputError."""
    if not isinstance(scene_id, str) or not SCENE_ID_RE.match(scene_id):
        raise InputError(
            f"scene id {scene_id!r} is not usable as a folder name "
            "(letters, digits, '.', '_', '-'; not starting with '.' or '-')", source)
    return scene_id


def collect_scenes(inputs: list[str | Path]) -> list[SceneSource]:
    """Expand ``mehs build`` arguments into scene sources (ids unique, order kept).

    Raises
    ------
    InputError
        For a missing path, an unknown kind of input, a bad scene list or
        duplicate scene ids.
    """
    out: list[SceneSource] = []
    for item in inputs:
        p = Path(item)
        if p.is_file() and p.suffix.lower() == ".csv":
            out.extend(read_scene_list_csv(p))
        elif p.is_file() and p.suffix.lower() == ".toml":
            out.extend(read_scene_list_toml(p))
        elif p.is_dir() and (p / "scene.json").is_file():
            out.append(_scene_folder(p))
        elif p.is_dir():
            subs = sorted(d for d in p.iterdir() if (d / "scene.json").is_file())
            if not subs:
                raise InputError("not a scene folder (no scene.json) and holds no scene "
                                 "folders", p)
            out.extend(_scene_folder(d) for d in subs)
        elif not p.exists():
            raise InputError("no such file or folder", p)
        else:
            raise InputError("expected a scene folder, a folder of scene folders, or a "
                             ".csv/.toml scene list", p)
    return _unique(out)


def collect_hs_cubes(inputs: list[str | Path]) -> list[SceneSource]:
    """Expand ``mehs build --from-hs`` arguments (``.hdr`` files or folders of them)."""
    out: list[SceneSource] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            from mehs.io.envi import header_files

            # any case, as the ENVI reader takes them: glob("*.hdr") left x.HDR cubes out
            hdrs = header_files(p)
            if not hdrs:
                raise InputError("folder holds no ENVI .hdr files", p)
        elif p.is_file():
            from mehs.io.envi import find_header_file

            hdrs = [find_header_file(p)]  # x.hdr, x.HDR or <data name>.hdr
        else:
            raise InputError("no such file or folder", p)
        out.extend(SceneSource(check_scene_id(h.stem, h), "hs", (str(h.resolve()),))
                   for h in hdrs)
    return _unique(out)


def _scene_folder(folder: Path) -> SceneSource:
    meta_path = folder / "scene.json"
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read scene.json ({exc})", meta_path) from None
    sid = meta.get("scene_id") if isinstance(meta, dict) else None
    if sid is None:
        sid = folder.name
    return SceneSource(check_scene_id(str(sid), meta_path), "scene", (str(folder.resolve()),))


def _specim(scene_id: str, folders: list[str], base: Path, where: str) -> SceneSource:
    check_scene_id(scene_id, where)
    if len(folders) < 2:
        raise InputError(f"scene {scene_id!r} names {len(folders)} folder(s); a bracket "
                         "needs at least two", where)
    paths = []
    for f in folders:
        q = Path(f).expanduser()
        q = q if q.is_absolute() else base / q
        if not q.is_dir():
            raise InputError(f"scene {scene_id!r}: Specim IQ folder not found: {q}", where)
        paths.append(str(q.resolve()))
    return SceneSource(scene_id, "specim", tuple(paths))


def read_scene_list_csv(path: str | Path) -> list[SceneSource]:
    """Read a CSV scene list (columns :data:`SCENE_LIST_COLUMNS`)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read scene list ({exc})", path) from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.DictReader(lines, skipinitialspace=True)
    cols = [c.strip() for c in (reader.fieldnames or [])]
    missing = [c for c in SCENE_LIST_COLUMNS if c not in cols]
    if missing:
        raise InputError(f"scene list lacks column(s) {missing}; expected header "
                         f"{','.join(SCENE_LIST_COLUMNS)}", path)
    out = []
    for n, row in enumerate(reader, start=2):
        row = {(k or "").strip(): (v or "").strip() for k, v in row.items()}
        folders = [row[c] for c in SCENE_LIST_COLUMNS[1:]]
        if not all(folders):
            raise InputError(f"row {n}: every folder column must be filled", path)
        out.append(_specim(row["scene_id"], folders, path.parent, f"{path}:{n}"))
    if not out:
        raise InputError("scene list names no scenes", path)
    return out


def read_scene_list_toml(path: str | Path) -> list[SceneSource]:
    """Read a TOML scene list (``[[scene]]`` tables with ``id`` and ``folders``)."""
    import tomllib

    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"cannot read scene list ({exc})", path) from None
    scenes = data.get("scene")
    if not isinstance(scenes, list) or not scenes:
        raise InputError("scene list has no [[scene]] tables", path)
    out = []
    for n, s in enumerate(scenes, start=1):
        if not isinstance(s, dict) or "id" not in s or not isinstance(s.get("folders"), list):
            raise InputError(f"[[scene]] #{n} needs id = \"...\" and folders = [...]", path)
        out.append(_specim(str(s["id"]), [str(f) for f in s["folders"]], path.parent,
                           f"{path} [[scene]] #{n}"))
    return out


def _unique(sources: list[SceneSource]) -> list[SceneSource]:
    seen: dict[str, SceneSource] = {}
    for s in sources:
        if s.scene_id in seen:
            raise InputError(f"scene id {s.scene_id!r} is given twice "
                             f"({seen[s.scene_id].paths[0]} and {s.paths[0]})")
        seen[s.scene_id] = s
    return sources
