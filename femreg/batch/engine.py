"""The engine of :mod:`femreg.batch`: independent tasks (:class:`Task`) on a Dask ``distributed`` cluster, or one
after the other in this process (``workers=0``); a failing task becomes a :class:`TaskOutcome` with its error.
"""
from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass, field
from typing import Any, Callable

from ..errors import InputError

__all__ = ["Task", "TaskOutcome", "run_tasks", "open_client", "WORKER_ENV"]


@dataclass
class Task:
    """One unit of work: ``func(*args, **kwargs)`` on a worker.  ``func`` must be importable on the workers
    (a module-level function of an installed package); its arguments and return value are pickled, so keep them
    small (paths, settings) and let ``func`` read and write the large data itself.  Larger ``priority`` runs
    first (put long tasks first for a short tail)."""

    key: str
    func: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    priority: int = 0


@dataclass
class TaskOutcome:
    """What became of a :class:`Task`: ``value`` (the function's return) or ``error`` ("Type: message")."""

    key: str
    value: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


@contextlib.contextmanager
def open_client(workers: int = 2, scheduler: str | None = None, *, memory_limit="auto"):
    """A Dask client for the duration of a ``with`` block, or None for ``workers=0`` (serial, no Dask).

    ``scheduler``: address of a running scheduler (``tcp://host:8786``, or a scheduler file path ending in
    .json); its workers are used as they are.  Otherwise a :class:`~distributed.LocalCluster` of ``workers``
    processes, one thread each, is started and closed at the end; ``memory_limit`` per worker (Dask's "auto" =
    the machine's memory divided by the workers; a worker above 95 % of it is restarted by its nanny).
    """
    if scheduler is None and int(workers) < 0:
        raise InputError(f"workers must be >= 0, got {workers}")
    if scheduler is None and int(workers) == 0:
        yield None
        return
    import logging

    from ..optional import require

    distributed = require("distributed", feature="femreg batch")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    if scheduler is not None:
        kw = {"scheduler_file": scheduler} if str(scheduler).endswith(".json") else {"address": scheduler}
        try:
            client = Client(timeout="20s", **kw)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"cannot connect to the Dask scheduler {scheduler} ({exc})") from None
        with client:
            try:  # tasks would wait forever on a scheduler without workers
                client.wait_for_workers(1, timeout=60)
            except TimeoutError:
                raise InputError(f"the Dask scheduler {scheduler} has no workers (waited 60 s)") from None
            yield client
        return
    # processes: the registration holds the GIL most of the time, threads would not run in parallel.
    # No dashboard: it needs bokeh, and a batch is watched through its progress bar.
    try:
        with _worker_environment():
            cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                   dashboard_address=None, memory_limit=memory_limit, silence_logs=logging.ERROR)
    except RuntimeError as exc:
        main = getattr(sys.modules.get("__main__"), "__file__", None)
        hint = (f"; if {main} is a script, put its main code under 'if __name__ == \"__main__\":' (Dask starts "
                f"workers by spawn, which imports the script)") if main else ""
        raise RuntimeError(f"could not start {workers} local Dask workers ({exc}){hint}") from exc
    with cluster, Client(cluster) as client:
        yield client


#: Environment of local worker processes: one BLAS / OpenMP thread each (N processes use N cores).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "VECLIB_MAXIMUM_THREADS": "1"}


@contextlib.contextmanager
def _worker_environment():
    """While local nannies are created: :data:`WORKER_ENV` for the workers they spawn (and respawn), overriding
    this process's values, which Dask would otherwise pass on; and without Dask's ``MALLOC_TRIM_THRESHOLD_``
    (64 KiB), which switches off glibc's adaptive mmap threshold: every array over 128 KiB is then mapped and
    unmapped afresh, 12 x the page faults and ~45 % more CPU time per paper-size registration (measured)."""
    import dask

    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    env.update(WORKER_ENV)
    env["MALLOC_TRIM_THRESHOLD_"] = None  # Dask's way to leave a variable unset
    saved = {k: os.environ.get(k) for k in WORKER_ENV}
    os.environ.update(WORKER_ENV)  # Dask prefers this process's values to its config: set them for the spawn
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": env}):
            yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _describe_error(exc: BaseException) -> str:
    msg = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _bar(total, desc, progress):
    if not progress:
        return None
    from ..progress import bar

    return bar(total=total, desc=desc, unit="task", smoothing=0.1)


def run_tasks(tasks, *, client=None, workers: int = 2, scheduler: str | None = None, progress: bool = True,
              desc: str = "tasks", on_result: Callable | None = None, memory_limit="auto") -> dict:
    """Run independent :class:`Task` s; returns ``{key: TaskOutcome}`` (every key, in the order given).

    Parameters
    ----------
    tasks : iterable of Task
        Keys must be unique.
    client : distributed.Client, optional
        Use this client (its cluster stays up).  Otherwise :func:`open_client` (``workers``, ``scheduler``,
        ``memory_limit``) opens one for this call; ``workers=0`` runs the tasks in this process, in order.
    progress : bool
        tqdm progress bar on stderr (``desc`` its label).
    on_result : callable(TaskOutcome), optional
        Called in this process as each task finishes (completion order).
    """
    tasks = list(tasks)
    keys = [t.key for t in tasks]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise InputError(f"task keys must be unique; repeated: {dup[:5]}")
    outcomes: dict = {}
    if not tasks:
        return outcomes
    if client is None:
        # no more local workers than tasks: each costs a process start and the imports
        with open_client(min(int(workers), len(tasks)), scheduler, memory_limit=memory_limit) as cl:
            if cl is None:
                return _run_serial(tasks, progress, desc, on_result)
            return run_tasks(tasks, client=cl, progress=progress, desc=desc, on_result=on_result)
    return _run_dask(tasks, client, progress, desc, on_result)


def _run_serial(tasks, progress, desc, on_result):
    outcomes = {}
    bar = _bar(len(tasks), desc, progress)
    try:
        for t in sorted(tasks, key=lambda t: -t.priority):
            try:
                out = TaskOutcome(t.key, value=t.func(*t.args, **t.kwargs))
            except Exception as exc:  # noqa: BLE001 - a failed task is reported, the others go on
                out = TaskOutcome(t.key, error=_describe_error(exc))
            outcomes[t.key] = out
            if on_result is not None:
                on_result(out)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return {t.key: outcomes[t.key] for t in tasks}


def _run_dask(tasks, client, progress, desc, on_result):
    import uuid

    from distributed import as_completed

    run_id = uuid.uuid4().hex[:8]
    futures = {}
    for t in tasks:
        # pure=False and a fresh key: a task is run for its side effects (files), never served from a cache.
        fut = client.submit(t.func, *t.args, **t.kwargs, key=f"femreg-{run_id}-{t.key}", pure=False,
                            priority=int(t.priority))
        futures[fut] = t.key
    outcomes = {}
    bar = _bar(len(tasks), desc, progress)
    n_err = 0
    try:
        for fut in as_completed(list(futures)):
            key = futures[fut]
            try:
                out = TaskOutcome(key, value=fut.result())
            except Exception as exc:  # noqa: BLE001 - the task raised, or its worker died too often (KilledWorker)
                out = TaskOutcome(key, error=_describe_error(exc))
                n_err += 1
            fut.release()
            outcomes[key] = out
            if on_result is not None:
                on_result(out)
            if bar is not None:
                if n_err:
                    bar.set_postfix_str(f"{n_err} failed")
                bar.update(1)
    except BaseException:
        client.cancel(list(futures))
        raise
    finally:
        if bar is not None:
            bar.close()
    return {t.key: outcomes[t.key] for t in tasks}
