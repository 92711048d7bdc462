"""Dataset records free of where the build machine kept the inputs.

A lab copies datasets between machines and compares builds by their bytes. The same
captures built from another folder (a copy, another user's home, another lab's disk)
are the same inputs, so everything but the volatile ``provenance.run`` of each manifest
entry — and every data file, ``fusion.json`` included, whose hash the manifest holds —
must be the same bytes (docs/formats.md, "Volatile fields"). Absolute paths broke
that: ``fusion.json`` recorded the scene folder (``source``) and the calibration file
(``calibration.path``), the entry its input folders and the ``--response`` /
``--calibration`` files. Here the paths this run read go into ``run`` and the rest
names the files; their contents stay identified by their SHA-256 (``input_sha256``,
``response_sha256``, the manifest's ``calibration.sha256``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

#: ``provenance.params`` entries that are file paths (moved to ``run``, named by file name)
PATH_PARAMS = ("response", "calibration")


def portable_provenance(paths: Iterable[str | Path], params: dict[str, Any],
                        run: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """``(inputs, params)`` for a manifest entry's ``provenance``; sets ``run``'s paths.

    Parameters
    ----------
    paths
        The scene's input paths as this build read them (absolute).
    params
        The build parameters (``asdict(BuildParams)``); not modified.
    run
        The entry's volatile ``provenance.run``: gets ``inputs`` (the absolute input
        paths) and, when given, ``response`` and ``calibration`` (their absolute paths).

    Returns
    -------
    The inputs' file or folder names, and ``params`` with ``response`` / ``calibration``
    reduced to their file names.
    """
    paths = [str(p) for p in paths]
    run["inputs"] = paths
    out = dict(params)
    for name in PATH_PARAMS:
        if out.get(name):
            run[name] = str(out[name])
            out[name] = Path(out[name]).name
    return [Path(p).name for p in paths], out


def portable_summary(summary: dict[str, Any]) -> dict[str, Any]:
    """A fusion summary for the dataset's ``fusion.json``: without ``source`` (the scene
    folder's absolute path) and ``calibration.path`` (the calibration is identified by its
    ``sha256``). ``summary`` is not modified."""
    out = {k: v for k, v in summary.items() if k != "source"}
    cal = out.get("calibration")
    if isinstance(cal, dict) and "path" in cal:
        out["calibration"] = {k: v for k, v in cal.items() if k != "path"}
    return out
