"""Thread-local warning rules (session 21 review): scene code that ignored or raised
warnings with catch_warnings could, in a threaded build, leave a blanket "ignore" in the
process-wide filters and silence every later warning of every scene."""

import logging
import threading
import warnings

import pytest

from mehs.dataset.scene_warnings import captured_warnings
from mehs.threadwarn import installed, local_filter


def test_overlapping_local_ignores_in_two_capturing_threads_leak_nothing():
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    logs, errors = {}, []

    def scene(name, first):
        try:
            with captured_warnings() as log:
                logs[name] = log
                with local_filter("ignore"):
                    warnings.warn(f"solver noise {name}", UserWarning)      # ignored
                    if first:
                        a_in.set()
                        b_in.wait(timeout=60)
                    else:
                        a_in.wait(timeout=60)
                        b_in.set()
                        a_out.wait(timeout=60)   # a leaves its block first: out of order
                if first:
                    a_out.set()
                warnings.warn(f"after the solve {name}", UserWarning)     # kept
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
            a_in.set(), b_in.set(), a_out.set()

    before = list(warnings.filters)
    ts = [threading.Thread(target=scene, args=("a", True)),
          threading.Thread(target=scene, args=("b", False))]
    for t in ts:
        t.start()
    for t in ts:
        t.join(timeout=120)
    assert not errors, errors
    assert [w["message"] for w in logs["a"]] == ["after the solve a"]
    assert [w["message"] for w in logs["b"]] == ["after the solve b"]
    assert warnings.filters == before and not installed()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        warnings.warn("later", UserWarning)
    assert [str(w.message) for w in seen] == ["later"]


def test_local_error_raises_in_its_thread_only():
    class Odd(UserWarning):
        pass

    other_seen, go, done = [], threading.Event(), threading.Event()

    def other():
        with captured_warnings() as log:
            go.wait(timeout=60)
            warnings.warn(Odd("elsewhere"))
            other_seen.extend(log)
            done.set()

    t = threading.Thread(target=other)
    t.start()
    with captured_warnings():
        with local_filter("error", Odd):
            go.set()
            done.wait(timeout=60)
            with pytest.raises(Odd, match="here"):
                warnings.warn(Odd("here"))
    t.join(timeout=60)
    assert [w["message"] for w in other_seen] == ["elsewhere"]


def test_local_filter_without_the_dispatcher_is_a_plain_catch_warnings():
    assert not installed()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with local_filter("ignore", UserWarning):
            warnings.warn("hidden", UserWarning)
        warnings.warn("shown", UserWarning)
    assert [str(w.message) for w in seen] == ["shown"]


def test_a_dispatcher_left_behind_does_not_recurse(monkeypatch):
    """logging.captureWarnings wraps showwarning during a capture and restores it after:
    the dispatcher stays installed; the next capture must not forward to itself."""
    shown = []
    monkeypatch.setattr(warnings, "_showwarnmsg_impl", lambda msg: shown.append(str(msg.message)))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        monkeypatch.setattr(warnings, "showwarning", warnings._showwarning_orig)
        with captured_warnings():
            logging.captureWarnings(True)
        logging.captureWarnings(False)
        assert installed()                                    # left behind
        with captured_warnings():
            warnings.warn("old API", DeprecationWarning)      # forwarded, not kept
        warnings.warn("plain", UserWarning)
    assert shown == ["old API", "plain"]
