"""Reading the small versioned JSON documents mehs writes (curves, calibrations)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mehs.errors import FormatError, InputError


def read_json_document(path: str | Path, fmt: str, what: str) -> dict[str, Any]:
    """The JSON object in ``path`` whose ``"format"`` is ``fmt``; errors name the file and ``what``."""
    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{what} file not found", path) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"not a readable JSON {what} ({exc})", path) from None
    if not isinstance(d, dict) or d.get("format") != fmt:
        got = d.get("format") if isinstance(d, dict) else None
        raise FormatError(f"not a {fmt} file (format = {got!r})", path)
    return d
