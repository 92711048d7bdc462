"""Thread-local warning control: what one thread's code may do to warnings without
touching the process-wide filters another thread relies on.

:class:`warnings.catch_warnings` saves and restores the process-wide filter list; two
threads that overlap such blocks out of order restore each other's copies, so one's
``simplefilter("ignore")`` can outlive both and silence every later warning of the process
(the dataset build runs scenes as threads under Dask). Here a process-wide dispatcher
(``warnings.showwarning``), installed while any thread holds :func:`hooked`, applies
per-thread rules (:func:`local_filter`) and hands warnings to a per-thread sink
(:mod:`mehs.dataset.scene_warnings` collects a scene's warnings that way). Without the
dispatcher — a single-threaded command — :func:`local_filter` is a plain
``catch_warnings``. The user's filters (``-W``, ``PYTHONWARNINGS``) keep precedence:
the one "always" entry the dispatcher needs (so the "default" action's once-per-place
memory does not hide a warning from the sink) is appended after them, and removed with
the dispatcher, if still in place, when the last holder leaves. A warning that reaches
the display only through that entry — another thread's, or one no sink keeps — is shown
as Python's default action would show it: once per place (``"default"``), per module
(``"module"``) or at all (``"once"``), as the filters the entry stands behind say; so a
merge's worker threads do not print one line per chunk while a build runs.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import warnings
from typing import Any, Callable, Iterator

_LOCK = threading.Lock()
_LOCAL = threading.local()
_active = 0
_forward: Any = None       # the display in place when the dispatcher was installed
_added: Any = None         # the "always" filter entry appended, if it was
_ALWAYS = ("always", None, Warning, None, 0)
_shown: set[tuple] = set()      # warnings shown once by the rule the "always" entry hides
_MODULES: dict[str, str] = {}   # file → module name


def _rules() -> list[tuple[str, tuple[type, ...]]]:
    r = getattr(_LOCAL, "rules", None)
    if r is None:
        r = _LOCAL.rules = []
    return r


def _dispatch(message, category, filename, lineno, file=None, line=None):
    for action, cats in reversed(_rules()):          # innermost rule first
        if issubclass(category, cats):
            if action == "ignore":
                return None
            # "error": raised from warnings.warn, as the filter would
            raise message if isinstance(message, Warning) else category(message)
    sink: Callable | None = getattr(_LOCAL, "sink", None)
    if sink is not None and sink(message, category):
        return None
    if _added is not None and not _first_time(message, category, filename, lineno):
        return None
    forward = _forward if _forward is not None else warnings._showwarning_orig  # type: ignore[attr-defined]
    return forward(message, category, filename, lineno, file, line)


def _module_name(filename: str) -> str:
    """The module a warning's file is (what the filters' module patterns match)."""
    name = _MODULES.get(filename)
    if name is None:
        for m in list(sys.modules.values()):
            if getattr(m, "__file__", None) == filename:
                name = m.__name__
                break
        else:   # as warnings.warn_explicit does without a module
            name = filename[:-3] if filename.endswith(".py") else filename
        _MODULES[filename] = name
    return name


def _first_time(message, category, filename, lineno) -> bool:
    """Whether a warning the display gets is to be shown: always, unless only the appended
    "always" entry let it through and the action it stands in for shows it once."""
    text = str(message)
    module = _module_name(filename)
    action = warnings.defaultaction
    for entry in warnings.filters:
        if entry is _added:
            break
        act, msg, cat, mod, ln = entry
        if ((msg is None or msg.match(text)) and issubclass(category, cat)
                and (mod is None or mod.match(module)) and (ln == 0 or lineno == ln)):
            return True        # the user's (or Python's) own entry decided
    if action == "once":
        key: tuple = (text, category)
    elif action == "module":
        key = (text, category, module)
    elif action == "default":
        key = (text, category, module, lineno)
    else:
        return True
    with _LOCK:
        if key in _shown:
            return False
        _shown.add(key)
    return True


def _filters_changed() -> None:
    # the per-module "already shown" registries are keyed on the filters' version
    bump = getattr(warnings, "_filters_mutated", None)
    if bump is not None:
        bump()


def installed() -> bool:
    """Whether the dispatcher is in place (some thread holds :func:`hooked`)."""
    return warnings.showwarning is _dispatch


@contextlib.contextmanager
def hooked(sink: Callable[[Any, type], bool] | None = None) -> Iterator[None]:
    """Hold the dispatcher for the block; ``sink(message, category)`` sees this thread's
    warnings first (True: consumed, not shown)."""
    global _active, _forward, _added
    with _LOCK:
        if _active == 0:
            # a dispatcher left in place by someone's out-of-order restore is not a display
            _forward = None if warnings.showwarning is _dispatch else warnings.showwarning
            warnings.showwarning = _dispatch
            _added = None
            if _ALWAYS not in warnings.filters:
                warnings.filters.append(_ALWAYS)
                _added = _ALWAYS
                _filters_changed()
        _active += 1
    previous = getattr(_LOCAL, "sink", None)
    _LOCAL.sink = sink
    try:
        yield
    finally:
        _LOCAL.sink = previous
        with _LOCK:
            _active -= 1
            if _active == 0:
                if warnings.showwarning is _dispatch:
                    warnings.showwarning = _forward if _forward is not None else \
                        warnings._showwarning_orig  # type: ignore[attr-defined]
                if _added is not None:
                    for i in range(len(warnings.filters) - 1, -1, -1):
                        if warnings.filters[i] == _added:
                            del warnings.filters[i]
                            _filters_changed()
                            break
                _forward = _added = None
                _shown.clear()   # Python's own registries take over again


@contextlib.contextmanager
def local_filter(action: str, *categories: type) -> Iterator[None]:
    """``action`` (``"ignore"`` or ``"error"``) for ``categories`` raised by this thread in
    the block, leaving other threads' warnings alone (see the module notes)."""
    if action not in ("ignore", "error"):
        raise ValueError(f"local_filter action must be 'ignore' or 'error', got {action!r}")
    cats = tuple(categories) or (Warning,)
    if not installed():
        with warnings.catch_warnings():
            for c in cats:
                warnings.simplefilter(action, c)
            yield
        return
    rules = _rules()
    rules.append((action, cats))
    try:
        yield
    finally:
        rules.pop()   # blocks nest in one thread: this one's rule is the last
