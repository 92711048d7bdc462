"""What a rebuild may reuse, what it must remove, and what it tells the user it changed.

A scene already in the manifest is reused only when its outputs still match the
SHA-256 recorded for them (cheaply via their recorded ``[size, mtime_ns]``,
:mod:`mehs.io.filecheck`); a damaged scene is named and rebuilt. Scenes that move
between splits because the split cuts moved (scenes were added) are named too.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mehs.errors import MehsError


def outputs_intact(dataset: Path, entry: dict, *, full: bool) -> bool:
    """True when every output file of ``entry`` still has its recorded SHA-256.

    Cheap for files whose ``[size, mtime_ns]`` (``provenance.run.output_stat``)
    is unchanged; hashed otherwise or with ``full``. A damaged scene is named
    on stderr and rebuilt, never reused.
    """
    from mehs.io.filecheck import verify_files

    run = (entry.get("provenance") or {}).get("run")
    try:
        stats = verify_files(dataset, entry.get("files") or {}, entry.get("sha256") or {},
                             stats=(run or {}).get("output_stat"), full=full,
                             what=f"scene {entry['id']!r}")
    except MehsError as exc:
        print(f"mehs build: {exc}; rebuilding the scene", file=sys.stderr)
        return False
    if isinstance(run, dict):
        run["output_stat"] = stats
    return True


def record_output_stat(dataset: Path, entry: dict) -> None:
    """Store ``[size, mtime_ns]`` of each output in the entry's volatile ``provenance.run``."""
    from mehs.io.filecheck import file_stat

    entry["provenance"]["run"]["output_stat"] = {
        rel: file_stat(dataset / rel) for rel in sorted((entry.get("files") or {}).values())}


def split_of(manifest: dict) -> dict[str, str]:
    """``{scene id: split name}`` of a manifest's splits."""
    return {sid: name for name, ids in (manifest.get("splits") or {}).items() for sid in ids}


def moved_between_splits(old: dict[str, str], new: dict[str, str]) -> list[tuple[str, str, str]]:
    """``(id, old split, new split)`` of scenes in a split before and after, sorted by id."""
    return [(sid, old[sid], new[sid]) for sid in sorted(old) if sid in new and new[sid] != old[sid]]


def remove_stale_temp_files(dataset: Path) -> list[str]:
    """Remove temporary files of atomic writes (``.<name>.*.part*``) a killed build left.

    :func:`mehs.io.atomic.write_text_atomic` and friends write ``.<name>.<random>.part<ext>``
    beside the target and rename it; a SIGKILL between the two leaves it behind, in the
    dataset folder (manifest, index) or ``splits/``. Call it with the build lock held.
    """
    gone = []
    for folder in (dataset, dataset / "splits"):
        if folder.is_dir():
            for f in sorted(folder.glob(".*.part*")):
                if f.is_file():
                    f.unlink(missing_ok=True)
                    gone.append(f.relative_to(dataset).as_posix())
    return gone
