"""The machine load a benchmark saw, printed beside its numbers (issue 16).

Timings on a shared machine mean little without it: :func:`load_line` gives the
1/5/15-minute load averages and, with psutil (the ``bench`` extra), the share
of the CPUs that *other* processes used over a short window.
"""

from __future__ import annotations

import os


def others_cpu(window_s: float = 0.5) -> float | None:
    """CPUs' worth of work done by other processes over ``window_s`` (0 … cpu_count), or None."""
    try:
        import psutil
    except ImportError:
        return None
    me = psutil.Process()
    own0 = me.cpu_times()
    psutil.cpu_percent(None)
    busy = psutil.cpu_percent(window_s) / 100 * (os.cpu_count() or 1)
    own1 = me.cpu_times()
    own = ((own1.user + own1.system) - (own0.user + own0.system)) / window_s
    return max(0.0, busy - own)


def load_line() -> str:
    """``"load average 1.52 1.10 0.98 on 2 CPUs; others busy 0.9 CPU"``."""
    la = " ".join(f"{x:.2f}" for x in os.getloadavg())
    text = f"load average {la} on {os.cpu_count()} CPUs"
    busy = others_cpu()
    if busy is not None:
        text += f"; other processes busy {busy:.2f} CPU"
    return text


def run_reporting_load(main) -> None:
    """Run ``main()`` between a "before:" and an "after:" load line; exit with its status."""
    print("before:", load_line(), flush=True)
    rc = main()
    print("after: ", load_line())
    raise SystemExit(rc)
