"""Process workers ignore Ctrl-C: the parent takes it and kills them, instead of each
starting worker printing its own KeyboardInterrupt traceback."""

import signal

from mehs.dataset.parallel import run_tasks


def _disposition(_):
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN


def test_process_workers_ignore_sigint_and_the_parent_keeps_its_handler():
    before = signal.getsignal(signal.SIGINT)
    got = list(run_tasks(_disposition, [("a", 0), ("b", 1), ("c", 2)], workers=2))
    assert got == [True, True, True]
    assert signal.getsignal(signal.SIGINT) is before
