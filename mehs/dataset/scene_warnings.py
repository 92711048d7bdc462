"""Warnings raised while a scene is built: kept with the scene, shown as one line each.

Left to Python, a build worker prints each warning raw on stderr (``file:line: Category:
message`` and the source line), the workers' lines interleaved and none naming the
scene; and a warning raised again at the same place in the same worker process (the
next scene it builds) is not shown at all. :func:`captured_warnings` collects, instead,
every warning the building thread raises, however often; the worker returns them with
the scene's result, the build records them in the scene's manifest entry
(``provenance.run.warnings``) and prints one line per warning naming the scene
(:func:`describe`).

Thread-safe: Dask runs scenes in threads of one process, and
:class:`warnings.catch_warnings` is process-global (each thread's exit would restore
the state another thread's entry saw). The capture rides on the dispatcher of
:mod:`mehs.threadwarn`, which hands each warning to the list of the thread that raised
it; scene code ignores or raises warnings for its own thread only
(:func:`mehs.threadwarn.local_filter`). The user's own filters (``-W``,
``PYTHONWARNINGS``) keep precedence. Warnings of threads a scene itself starts are
shown, not captured.
"""

from __future__ import annotations

import contextlib
import functools
import re
from typing import Any, Iterator

#: distinct warnings kept per scene; the rest are counted
MAX_KEPT = 20

# ignored by Python's default filters (PEP 565): library deprecations are not the scene's
_QUIET = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)

def _keep(log: list[dict[str, Any]], message, category) -> bool:
    """Add a warning to ``log``; True when kept (the sink of :func:`mehs.threadwarn.hooked`)."""
    if issubclass(category, _QUIET):
        return False       # a library deprecation (not the scene's): shown as before
    name = category.__name__ if category.__module__ == "builtins" else (
        f"{category.__module__}.{category.__qualname__}")
    text = str(message)
    for w in log:
        if w["category"] == name and w["message"] == text:
            w["count"] += 1
            return True
    log.append({"category": name, "message": text, "count": 1})
    return True


@contextlib.contextmanager
def captured_warnings() -> Iterator[list[dict[str, Any]]]:
    """Collect the warnings this thread raises inside the block.

    Yields
    ------
    list of dict
        Filled in as warnings come: ``{"category": qualified class name (builtins
        bare), "message": str, "count": times raised}``, distinct (category, message)
        pairs in the order first raised; complete once the block is left (at most
        :data:`MAX_KEPT` entries, a last ``"mehs.more"`` entry counting the rest).
        Deprecation, import and resource warnings are shown as before, not collected.

    Notes
    -----
    Built on :mod:`mehs.threadwarn`: the user's filters keep precedence (``-W
    error::RuntimeWarning`` still raises, ``ignore`` still ignores), no process-wide
    :class:`warnings.catch_warnings` is entered, and scene code that must ignore or
    raise a warning does so for its own thread (:func:`mehs.threadwarn.local_filter`).
    """
    from mehs.threadwarn import hooked

    log: list[dict[str, Any]] = []
    try:
        # the sink is this thread's (threadwarn keeps it per thread, nested blocks included)
        with hooked(functools.partial(_keep, log)):
            yield log
    finally:
        if len(log) > MAX_KEPT:
            rest = sum(w["count"] for w in log[MAX_KEPT:])
            log[MAX_KEPT:] = [{"category": "mehs.more", "count": 1,
                               "message": f"{len(log) - MAX_KEPT} more distinct warning(s), "
                                          f"raised {rest} time(s), not kept"}]


def relocate_paths(log: list[dict[str, Any]], tmp_name: str, final_name: str,
                   parent: str = "scenes") -> list[dict[str, Any]]:
    """Rewrite, in place, the path component ``<parent>/<tmp_name>`` of the messages to
    ``<parent>/<final_name>``; return ``log``.

    A warning raised while building names the scene's temporary folder
    (``scenes/.tmp-<id>/hdr_rgb.exr``), which the commit renames to ``scenes/<id>``: kept
    as raised, the path it names no longer exists. Only that exact folder name after a
    ``parent`` component (``/`` or ``\\``) is rewritten: not ``.tmp-<id>0``, not the
    name elsewhere in the text.
    """
    # followed by a separator, the end, or a character no file name continues with
    # (a sentence's final dot is no part of the name)
    pattern = re.compile(r"(?<![^/\\\s\"'(])(" + re.escape(parent) + r"[/\\])"
                         + re.escape(tmp_name) + r"(?=[/\\]|$|[^\w.\-]|\.(?:\s|$))")
    for w in log:
        msg = w.get("message")
        if isinstance(msg, str) and tmp_name in msg:
            w["message"] = pattern.sub(lambda m: m.group(1) + final_name, msg)
    return log


def describe(w: dict[str, Any]) -> str:
    """One line for a recorded warning.

    mehs's own warnings are written for the user (what happened, what it means, what to
    do): their text alone; another library's keeps its class name (``RuntimeWarning:
    divide by zero encountered in log``), which is part of what it says.
    """
    cat = str(w.get("category", "Warning"))
    text = " ".join(str(w.get("message", "")).split())  # one line, whatever the message
    if not cat.startswith("mehs."):
        text = f"{cat.rsplit('.', 1)[-1]}: {text}"
    n = w.get("count", 1)
    return text + (f" (×{n})" if isinstance(n, int) and n > 1 else "")
