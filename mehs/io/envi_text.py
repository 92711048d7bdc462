"""The text of an ENVI header: bytes → text → ``key = value`` pairs.

SPy's rules (keys lower-cased, ``;`` comments, ``{…}`` split at commas,
``description`` kept whole), extended for what real writers produce: byte-order
marks, code page 1252, CR LF line ends, a brace block closed on its own line or
followed by stray text, a trailing comma. :mod:`mehs.io.envi` turns the pairs into
a checked :class:`~mehs.io.envi.EnviHeader`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Collection

from mehs.errors import FormatError, InputError


class HeaderSyntaxError(ValueError):
    """A ``{…}`` block that never closes."""


def decode_header(raw: bytes) -> str:
    """Header bytes → text, tolerating what real writers put there.

    Windows tools save headers with a UTF-8 or UTF-16 byte-order mark and
    in code page 1252 (``µm``, ``°C`` in descriptions); SPy's parser reads
    them with the locale's codec and rejects the BOM as "not ENVI".
    """
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8", errors="replace")
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16", errors="replace")
    if len(raw) >= 4 and raw[0] and not raw[1] and raw[2] and not raw[3]:
        # UTF-16 without its byte-order mark ("ENVI" as E\0N\0…): little-endian
        return raw.decode("utf-16-le", errors="replace")
    if len(raw) >= 4 and not raw[0] and raw[1] and not raw[2] and raw[3]:
        return raw.decode("utf-16-be", errors="replace")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("cp1252", errors="replace")


def parse_header_text(text: str, conflicts: dict[str, list[Any]] | None = None
                      ) -> dict[str, Any] | None:
    """``key = value`` / ``key = {…}`` pairs of an ENVI header text (``None``: not ENVI).

    The same reading as SPy's ``read_envi_header`` (keys lower-cased, ``;``
    comment lines, ``{…}`` split at commas, ``description`` kept whole),
    plus what real headers need: any line ending (CR LF from Specim
    Lumo/IQ software), a brace block closed on its own line or followed by
    stray text, and a trailing comma before ``}`` (no empty last item).

    A key given twice keeps its last value (SPy's rule). When ``conflicts`` is a
    dict, every key given twice *with different values* is recorded there as
    ``{key: [value, value, …]}`` (in file order), so that a caller can refuse a
    hand-edited header whose ``samples`` or ``wavelength`` is ambiguous.
    """
    lines = text.splitlines()
    if not lines or not lines[0].strip().startswith("ENVI"):
        return None
    out: dict[str, Any] = {}
    i = 1
    while i < len(lines):
        line = lines[i]
        i += 1
        if "=" not in line or line.lstrip().startswith(";"):
            continue
        key, _, val = line.partition("=")
        key, val = key.strip().lower(), val.strip()
        if not val.startswith("{"):
            _put(out, key, val, conflicts)
            continue
        parts = [val]
        depth = val.count("{") - val.count("}")
        while depth > 0:
            if i >= len(lines):
                raise HeaderSyntaxError(f"'{key}' = {{ … is never closed")
            nxt = lines[i].strip()
            i += 1
            if nxt.startswith(";"):
                continue
            parts.append(nxt)
            depth += nxt.count("{") - nxt.count("}")
        block = "\n".join(parts)
        # up to the brace that closes the first one; anything after is stray
        d = 0
        for j, ch in enumerate(block):
            d += (ch == "{") - (ch == "}")
            if d == 0:
                block = block[:j + 1]
                break
        inner = block[1:-1]
        if key == "description":
            _put(out, key, inner.strip(), conflicts)
            continue
        items = [v.strip() for v in inner.split(",")]
        if len(items) > 1 and items[-1] == "":
            items.pop()  # "{a, b,}": a trailing comma, not an empty last value
        _put(out, key, items, conflicts)
    return out


def _put(out: dict[str, Any], key: str, val: Any, conflicts: dict[str, list[Any]] | None) -> None:
    if conflicts is not None and key in out and _meaning(out[key]) != _meaning(val):
        conflicts.setdefault(key, [out[key]]).append(val)
    out[key] = val


def _meaning(val: Any) -> tuple:
    """What a value says, not how it is spelled: ``bil`` and ``BIL``, ``500`` and ``500.00``
    are one value (ENVI reads keywords and numbers so), so repeating a key with them is
    no conflict."""
    items = val if isinstance(val, list) else [val]
    out = []
    for item in items:
        text = str(item).strip()
        try:
            out.append(float(text))
        except ValueError:
            out.append(text.casefold())
    return tuple(out)


def read_header_pairs(hp: Path, strict_keys: Collection[str] = ()) -> dict[str, Any]:
    """The key/value pairs of the ENVI header file ``hp`` (named errors for unreadable or non-ENVI).

    A key of ``strict_keys`` given twice with different values is a
    :class:`FormatError`: which one the writer meant cannot be told (a line
    appended in a text editor, two headers pasted together), and taking the last
    would read the data with another shape or other band centres without a word.
    """
    try:
        raw = hp.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read header ({exc.strerror})", hp) from None
    if not raw.strip(b" \t\r\n\x00"):
        raise FormatError("not an ENVI header: the file is empty (an interrupted copy or a full "
                          "disk?)", hp)
    conflicts: dict[str, list[Any]] = {}
    try:
        h = parse_header_text(decode_header(raw), conflicts)
    except HeaderSyntaxError:
        raise FormatError("ENVI header cannot be parsed (unbalanced '{…}' or "
                          "binary content; a truncated copy?)", hp) from None
    if h is None:
        raise FormatError("not an ENVI header (first line is not 'ENVI')", hp)
    bad = [k for k in conflicts if k in strict_keys]
    if bad:
        k = bad[0]
        vals = " and ".join(_short(v) for v in conflicts[k])
        raise FormatError(f"header key '{k}' is given {len(conflicts[k])} times with different "
                          f"values ({vals}); remove the wrong line", hp)
    return h


def _short(val: Any) -> str:
    text = "{" + ", ".join(val) + "}" if isinstance(val, list) else str(val)
    return repr(text if len(text) <= 40 else text[:37] + "…")
