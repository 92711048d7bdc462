"""Run one function over many scene tasks: in-process, on local processes, or on Dask.

All three runners yield results *as they complete* and keep at most ``workers``
tasks in flight, so memory stays bounded by ``workers`` scenes whatever the
number of scenes. Workers report their current stage through
:func:`report_stage`; the caller receives ``(task_id, stage)`` via ``on_stage``.

Process workers are started with the ``spawn`` method (safe with threads,
numba and OpenEXR; the same on every OS), so the task function and its
argument must be importable/picklable. Workers die with the process that
started them (:mod:`mehs.dataset.lifetime`), ignore Ctrl-C (the parent takes it), and
an interrupted run kills them instead of waiting for their scenes. Each worker's BLAS/OpenMP/numba thread
count is set to ``cpu_count // workers`` (unless already set in the
environment) to avoid oversubscribing the cores.
"""

from __future__ import annotations

import contextlib
import os
import queue as queue_mod
from typing import Any, Callable, Iterable, Iterator

from mehs.dataset.lifetime import die_with_parent, kill_processes
from mehs.errors import MehsError

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")

#: Set in each process worker by :func:`_init_worker`; in-process runs use a callback.
_STAGE_SINK: Callable[[str, str], None] | None = None


def report_stage(task_id: str, stage: str) -> None:
    """Tell the runner (and its progress bar) that ``task_id`` entered ``stage``."""
    sink = _STAGE_SINK
    if sink is not None:
        with contextlib.suppress(Exception):  # progress must never break a build
            sink(task_id, stage)


def _init_worker(q, parent: int | None = None) -> None:
    global _STAGE_SINK
    if parent is not None:
        die_with_parent(parent)  # an orphan would write scenes/.tmp-* behind the next build
    _STAGE_SINK = lambda tid, stage: q.put_nowait((tid, stage))  # noqa: E731


def default_workers() -> int:
    """The number of CPUs this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def _thread_limits(workers: int):
    per = str(max(1, default_workers() // max(1, workers)))
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    for v in _THREAD_VARS:
        os.environ.setdefault(v, per)
    try:
        yield
    finally:
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old


@contextlib.contextmanager
def _sigint_ignored():
    """Workers started inside the block ignore SIGINT for their whole life.

    Ctrl-C reaches every process of the terminal's group: a worker still starting up then
    printed its own ``KeyboardInterrupt`` traceback (``spawn_main``) over the build's
    message. An ignored signal stays ignored across ``exec`` and Python leaves it so, so
    only the parent is interrupted and kills its workers (``_run_processes``). A Ctrl-C
    landing during the few milliseconds of a worker's start is lost; the next one works.
    Only the main thread may set signal handlers; elsewhere nothing changes.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        # None: a handler not installed from Python (an embedding application's); it
        # cannot be put back from here, and the default is the closest
        signal.signal(signal.SIGINT, old if old is not None else signal.SIG_DFL)


def run_tasks(fn: Callable[[Any], Any], tasks: Iterable[tuple[str, Any]], *,
              workers: int = 1, scheduler: Any = None,
              on_stage: Callable[[str, str], None] | None = None) -> Iterator[Any]:
    """Yield ``fn(arg)`` for each ``(task_id, arg)`` in ``tasks``, as each completes.

    Parameters
    ----------
    fn
        A module-level function (picklable for process/Dask runs).
    workers
        Tasks in flight at once; 1 (and no scheduler) runs in this process.
    scheduler
        ``None``, a Dask scheduler address (``"tcp://host:8786"``) or a
        ``distributed.Client``.
    on_stage
        Called in this process with ``(task_id, stage)`` as workers report stages
        (not available on Dask, where each task reports only its start).
    """
    tasks = list(tasks)
    if scheduler is not None:
        yield from _run_dask(fn, tasks, workers, scheduler, on_stage)
    elif workers <= 1 or len(tasks) <= 1:
        yield from _run_serial(fn, tasks, on_stage)
    else:
        yield from _run_processes(fn, tasks, workers, on_stage)


def _run_serial(fn, tasks, on_stage):
    global _STAGE_SINK
    old, _STAGE_SINK = _STAGE_SINK, on_stage
    try:
        for _tid, arg in tasks:
            yield fn(arg)
    finally:
        _STAGE_SINK = old


def _run_processes(fn, tasks, workers, on_stage):
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()

    def drain():
        while True:
            try:
                tid, stage = q.get_nowait()
            except (queue_mod.Empty, OSError, EOFError):
                return
            if on_stage is not None:
                on_stage(tid, stage)

    todo = list(reversed(tasks))
    with _thread_limits(workers), _sigint_ignored():
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                   initializer=_init_worker, initargs=(q, os.getpid()))
    finished = False
    try:
        pending = set()
        while todo or pending:
            while todo and len(pending) < workers:
                tid, arg = todo.pop()
                if on_stage is not None:
                    on_stage(tid, "queued")
                with _thread_limits(workers), _sigint_ignored():   # submit starts workers
                    pending.add(pool.submit(fn, arg))
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            drain()
            for fut in done:
                try:
                    yield fut.result()
                except BrokenProcessPool as exc:
                    raise MehsError(f"a build worker process died ({exc}); re-run to "
                                    "resume (out of memory? try fewer --workers)") from None
        finished = True
    finally:
        if not finished:  # Ctrl-C, an error, or the caller stopped iterating
            kill_processes((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=True, cancel_futures=True)
        q.close()


def _run_dask(fn, tasks, workers, scheduler, on_stage):
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise MehsError("--scheduler needs Dask distributed: pip install 'mehs[dask]'") from None
    own = not isinstance(scheduler, Client)
    try:
        client = Client(scheduler) if own else scheduler
    except (OSError, ValueError, TimeoutError) as exc:
        raise MehsError(f"cannot connect to the Dask scheduler ({exc})", scheduler) from None
    try:
        slots = workers if workers and workers > 1 else max(
            1, sum(client.nthreads().values()))
        todo = list(reversed(tasks))
        ac = as_completed()
        inflight = 0

        def submit():
            nonlocal inflight
            tid, arg = todo.pop()
            if on_stage is not None:
                on_stage(tid, "dask")
            ac.add(client.submit(fn, arg, pure=False))
            inflight += 1

        while todo and inflight < slots:
            submit()
        for fut in ac:
            inflight -= 1
            result = fut.result()
            fut.release()
            if todo:
                submit()
            yield result
    finally:
        if own:
            client.close()
