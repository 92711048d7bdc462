"""While a scene captures warnings, other threads' warnings keep Python's default
once-per-place display: the capture's appended "always" entry must not turn a merge's
worker threads (or the main thread) into one line per chunk."""

import threading
import warnings

import pytest

from mehs.dataset.scene_warnings import captured_warnings


def _warn_three_times(category=RuntimeWarning):
    for _ in range(3):
        warnings.warn("invalid value in a chunk", category)   # one place, three times


def _run_with_a_capturing_scene(body, setup):
    """Run ``body`` in another thread while this one holds a scene capture; return the
    lines the display printed."""
    shown = []
    with warnings.catch_warnings():
        warnings.resetwarnings()
        setup()
        warnings.showwarning = lambda m, c, f, ln, file=None, line=None: shown.append(str(m))
        with captured_warnings() as log:
            t = threading.Thread(target=body)
            t.start()
            t.join(timeout=60)
            warnings.warn("the scene's own", UserWarning)
            warnings.warn("the scene's own", UserWarning)
    # kept by the scene (twice, unless the user's own "once" filter shows it once)
    assert [w["message"] for w in log] == ["the scene's own"]
    return shown


@pytest.mark.parametrize("setup, expected", [
    (lambda: None, 1),                                          # Python's default action
    (lambda: warnings.simplefilter("default"), 1),
    (lambda: warnings.simplefilter("always"), 3),               # the user asked for every one
    (lambda: warnings.simplefilter("once"), 1),
    (lambda: warnings.simplefilter("ignore", RuntimeWarning), 0),
], ids=["no-filter", "default", "always", "once", "ignore"])
def test_another_threads_repeated_warning_follows_the_users_filters(setup, expected):
    shown = _run_with_a_capturing_scene(_warn_three_times, setup)
    assert shown == ["invalid value in a chunk"] * expected


def test_distinct_warnings_of_other_threads_are_each_shown():
    def body():
        for i in range(3):
            warnings.warn(f"chunk {i}", RuntimeWarning)

    shown = _run_with_a_capturing_scene(body, lambda: None)
    assert shown == ["chunk 0", "chunk 1", "chunk 2"]


def test_once_per_place_memory_ends_with_the_capture():
    with warnings.catch_warnings():
        warnings.resetwarnings()
        shown = []
        warnings.showwarning = lambda m, c, f, ln, file=None, line=None: shown.append(str(m))
        for _ in range(2):
            with captured_warnings():
                t = threading.Thread(target=_warn_three_times)
                t.start()
                t.join(timeout=60)
    # one per build: a later build's threads are shown their warning again
    assert shown == ["invalid value in a chunk"] * 2
