"""Worker processes that never outlive the process that started them.

A ``mehs build`` killed with SIGKILL cannot clean up: its pool workers (each
holding a scene of several hundred MB) used to live on as orphans, keep writing
``scenes/.tmp-*`` behind the next build's back and hold the parent's stdout
pipe open (a caller reading that pipe waited for them). Two independent guards
make a worker die with its parent:

* on Linux, ``prctl(PR_SET_PDEATHSIG, SIGKILL)``: the kernel kills the worker
  the moment its parent dies (no polling delay);
* everywhere, a daemon thread that polls the parent pid and ends the worker
  with ``os._exit`` when the worker has been re-parented.

References
----------
prctl(2), ``PR_SET_PDEATHSIG`` — Linux man-pages.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
#: Seconds between two checks of the parent pid by the watchdog thread.
POLL_S = 0.25


def _set_pdeathsig(sig: int) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux only)."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):  # pragma: no cover - exotic libc
        return False


def _watch_parent(parent: int, poll_s: float) -> None:
    while True:
        if os.getppid() != parent:
            os._exit(70)  # the parent is gone: finish nothing it could mistake as complete
        time.sleep(poll_s)


def die_with_parent(parent: int, *, poll_s: float = POLL_S) -> None:
    """Make this (worker) process exit as soon as process ``parent`` dies.

    Call it first thing in a worker (a pool ``initializer``). ``parent`` is the
    pid the starter passed down; if this process has already been re-parented
    (the parent died while it started) it exits at once.
    """
    _set_pdeathsig(signal.SIGKILL)
    if os.getppid() != parent:  # died between fork and prctl: the signal was never sent
        os._exit(70)
    threading.Thread(target=_watch_parent, args=(parent, poll_s), daemon=True,
                     name="mehs-parent-watchdog").start()


def kill_processes(processes) -> None:
    """SIGKILL each live ``multiprocessing.Process`` of ``processes`` and reap it.

    For an interrupted run (Ctrl-C, an error): the workers' half-built scenes are
    discarded anyway, so waiting for them to finish would only delay the exit.
    """
    procs = list(processes)
    for p in procs:
        with contextlib.suppress(Exception):
            if p.is_alive():
                p.kill()
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(timeout=5)
