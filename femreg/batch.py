"""Batches on Dask: many recordings registered or tracked in parallel, on this machine or on a cluster.

Two layers, one engine:

* :func:`run_tasks` runs independent tasks (a module-level function and its arguments each) on a Dask
  ``distributed`` cluster: a :class:`~distributed.LocalCluster` of ``workers`` processes with one thread each
  (default), an existing scheduler by address, or a :class:`~distributed.Client` the caller already holds;
  ``workers=0`` runs them one after the other in this process without Dask.  A task that raises, or whose worker
  dies too often (Dask's ``KilledWorker``), becomes a :class:`TaskOutcome` with the error; the others go on.
  The study (alpha sweeps and cases) runs on this engine too.
* :func:`run_batch` registers or tracks recordings (:class:`Job`, one per file or folder of frame files; one task
  per recording, or per frame pair with ``task="register"``).  Each task reads its input by path and writes its
  result atomically into ``OUT/<name>/`` on the worker, then its record (``*.record.json``) last; only the small
  record travels back to the client.  ``OUT/batch.json`` (the manifest) holds every job's settings;
  ``resume=True`` keeps finished tasks and refuses changed settings, as ``femreg track --resume`` does.
  ``OUT/summary.csv`` and ``OUT/summary.md`` list every task at the end.

Output names are deterministic (the recording's file or folder name; ``pair_III-JJJ.npz`` per registered pair;
``frame_KKK.npz`` + ``track.json`` per tracked recording, the folder layout of ``femreg track``).

Worker processes get one BLAS thread each (Dask's nanny sets ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` /
``MKL_NUM_THREADS`` to 1 before a worker starts: ``distributed.nanny.pre-spawn-environ``), so N workers use N
cores.  Every record carries the task's wall time and the peak resident memory of its worker process during the
task (Linux: ``VmHWM`` after resetting it through ``/proc/self/clear_refs``).

A worker that dies (killed, out of memory, node lost) loses no finished result: results are on disk before the
task ends, Dask reschedules the tasks the worker held, and a rescheduled task whose record is already written
returns it without recomputing; a track that was cut short continues from its last checkpointed frame.

Local scripts that call :func:`run_batch` / :func:`run_tasks` with a LocalCluster must guard their main code with
``if __name__ == "__main__":`` (Dask starts workers by *spawn*, which imports the calling script).
"""
from __future__ import annotations

import contextlib
import csv
import functools
import hashlib
import io
import json
import os
import socket
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ._atomic import atomic_savez, atomic_write_text
from .errors import InputError

__all__ = ["Task", "TaskOutcome", "run_tasks", "open_client", "Job", "jobs_from_inputs", "run_batch",
           "BatchSummary", "default_settings", "settings_keys", "settings_file_for", "MANIFEST"]

#: The manifest file of a batch folder.
MANIFEST = "batch.json"
_FORMAT = "femreg-batch 1"


# ================================================================================================================
# The engine: independent tasks on Dask
# ================================================================================================================

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

    from .optional import require

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
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="task", smoothing=0.1)


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


# ================================================================================================================
# Recordings: jobs, settings, per-input settings files
# ================================================================================================================

_TASK_DEFAULTS = {"task": "track", "pairs": [[0, 1]], "mode": "accumulate", "grid": "current", "init": "previous",
                  "min_ncc": 0.5}


@functools.lru_cache(maxsize=1)
def flag_defaults() -> tuple:
    """({registration flag: default}, {reader flag: default}) of the flags shared by ``femreg register`` /
    ``track`` (femreg/cli/_common.py): a batch takes exactly those settings, with the same defaults."""
    import argparse

    from .cli._common import add_reader_args, add_registration_args

    out = []
    for add in (add_registration_args, add_reader_args):
        p = argparse.ArgumentParser(add_help=False)
        add(p)
        out.append(vars(p.parse_args([])))
    return tuple(out)


def settings_keys() -> tuple:
    """Names of the settings a job (and a per-recording settings file) may set: the task's, then the shared
    registration and reader flags' (``--element-size`` -> ``element_size``)."""
    reg, reader = flag_defaults()
    return tuple(_TASK_DEFAULTS) + tuple(reg) + tuple(reader)


def default_settings() -> dict:
    """Every setting at its default: the defaults of the shared command-line flags, and ``task="track"``,
    ``pairs=[[0, 1]]``, ``mode="accumulate"``, ``grid="current"``, ``init="previous"``, ``min_ncc=0.5``."""
    reg, reader = flag_defaults()
    return json.loads(json.dumps({**_TASK_DEFAULTS, **reg, **reader}))  # a deep copy


def frames_text(sel):
    """A parsed frame selection back to its JSON form (int, list, or the 'a:b:c' text)."""
    if isinstance(sel, slice):
        return ":".join("" if v is None else str(v) for v in (sel.start, sel.stop, sel.step))
    if isinstance(sel, (list, tuple)):
        return [int(v) for v in sel]
    return sel


def _check_settings(settings: dict, where: str) -> dict:
    """Validate a flat settings dict (JSON types) with the command line's own checks; returns
    (reader kwargs, registration kwargs) for :func:`femreg.io.read_frames` and :func:`femreg.register`."""
    import argparse

    from .cli import _common

    unknown = sorted(set(settings) - set(settings_keys()))
    if unknown:
        raise InputError(f"{where}: unknown setting(s) {unknown}; known: {', '.join(settings_keys())}")
    s = dict(settings)
    def real(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    types = {"alpha": real, "margin": real, "hourglass": real, "tol": real, "sound_speed": real, "min_ncc": real,
             "maxiter": lambda v: isinstance(v, int) and not isinstance(v, bool),
             "element_size": lambda v: real(v) or (isinstance(v, (list, tuple)) and all(real(x) for x in v)),
             "shape": lambda v: isinstance(v, (list, tuple)) and all(isinstance(x, int) for x in v),
             "regularizer": lambda v: isinstance(v, str), "variable": lambda v: isinstance(v, str),
             "roi": lambda v: isinstance(v, str) or (isinstance(v, (list, tuple)) and all(real(x) for x in v)),
             "depth": lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(real(x) for x in v),
             "strategy": lambda v: isinstance(v, str), "no_orientation_check": lambda v: isinstance(v, bool),
             "dtype": lambda v: isinstance(v, str), "byte_order": lambda v: v in ("little", "big"),
             "frames": lambda v: isinstance(v, (int, str)) or (isinstance(v, (list, tuple))
                                                               and all(isinstance(x, int) for x in v))}
    bad = [k for k, ok in types.items() if s.get(k) is not None and not ok(s[k])]
    if bad:
        raise InputError(f"{where}: bad value(s) " + ", ".join(f"{k}={s[k]!r}" for k in bad))
    try:
        if s.get("frames") is not None and isinstance(s["frames"], str):
            s["frames"] = _common._frame_selection(s["frames"])
        if s.get("spacing") is not None:
            sp = s["spacing"]
            if not (isinstance(sp, (list, tuple)) and len(sp) == 2):
                raise InputError(f"{where}: spacing must be [dx, dy] in mm, got {sp!r}")
            s["spacing"] = [None if v is None else _common._spacing_value(str(v)) for v in sp]
    except argparse.ArgumentTypeError as exc:
        raise InputError(f"{where}: {exc}") from None
    for key in ("shape", "element_size"):
        v = s.get(key)
        if v is not None and not isinstance(v, (list, tuple)):
            s[key] = [v]
    try:
        ns = argparse.Namespace(**s)
        reader = _common.reader_kwargs(ns)
        reg = _common.registration_kwargs(ns)
    except (InputError, TypeError) as exc:
        raise InputError(f"{where}: {exc}") from None
    if s["task"] not in ("register", "track"):
        raise InputError(f"{where}: task must be 'register' or 'track', got {s['task']!r}")
    if s["mode"] not in ("accumulate", "direct") or s["grid"] not in ("current", "reference") \
            or s["init"] not in ("previous", "blockmatch"):
        raise InputError(f"{where}: mode/grid/init must be accumulate|direct, current|reference, "
                         f"previous|blockmatch; got {s['mode']!r}, {s['grid']!r}, {s['init']!r}")
    pairs = s["pairs"]
    if not (isinstance(pairs, (list, tuple)) and pairs and all(
            isinstance(p, (list, tuple)) and len(p) == 2 and all(isinstance(i, int) and i >= 0 for i in p)
            for p in pairs)):
        raise InputError(f"{where}: pairs must be a list of [reference, moving] frame indices >= 0, got {pairs!r}")
    return reader, reg


@dataclass(frozen=True)
class Job:
    """One recording: ``input`` (a frame file, or a folder of per-frame files, as :func:`femreg.io.read_frames`
    reads them), its output ``name`` (a folder of the batch output) and its ``settings``
    (:func:`settings_keys`; :func:`default_settings` fills the rest).  ``task="track"`` is one task;
    ``task="register"`` is one task per entry of ``settings["pairs"]``."""

    input: str
    name: str
    settings: dict = field(default_factory=dict)

    def resolved(self) -> dict:
        s = default_settings()
        s.update(self.settings)
        return s


def _read_settings_file(path: Path) -> dict:
    try:
        text = path.read_text()
        if path.suffix == ".toml":
            try:
                import tomllib
            except ImportError:  # Python 3.10
                raise InputError(f"{path}: TOML settings need Python >= 3.11; use JSON") from None
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read settings ({' '.join(str(exc).split())})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: settings must be a table/object of name = value")
    out = {}
    for k, v in data.items():
        key = k.replace("-", "_")
        if key == "pair":  # one pair, as the --pair flag
            key, v = "pairs", [v]
        out[key] = v
    return out


def settings_file_for(path) -> Path | None:
    """The per-recording settings file of ``path``: ``<name>.femreg.toml`` or ``<name>.femreg.json`` beside it
    (``<name>`` without the extension), or ``femreg.toml`` / ``femreg.json`` inside a folder recording."""
    path = Path(path)
    stem = path.name if path.is_dir() else path.stem
    cands = [path.with_name(f"{stem}.femreg.toml"), path.with_name(f"{stem}.femreg.json")]
    if path.is_dir():
        cands += [path / "femreg.toml", path / "femreg.json"]
    found = [c for c in cands if c.is_file()]
    if len(found) > 1:
        raise InputError(f"{path}: more than one settings file ({', '.join(str(f) for f in found)}); keep one")
    return found[0] if found else None


def _scan_folder(folder: Path, skip: Path | None) -> list[Path]:
    """The recordings of a folder: every frame file (supported extension) and every sub-folder, in name
    order; MetaImage data files (the .raw of a .mhd) and hidden entries are left out."""
    from .io.readers import FORMATS, natural_key

    entries = sorted((p for p in folder.iterdir() if not p.name.startswith(".")), key=lambda p: natural_key(p.name))
    data_files = set()
    for p in entries:
        if p.is_file() and p.suffix.lower() in (".mhd",):
            data_files.add(p.with_suffix(".raw").name)
            with contextlib.suppress(OSError, UnicodeDecodeError):
                for line in p.read_text(errors="strict").splitlines():
                    if line.replace(" ", "").lower().startswith("elementdatafile="):
                        data_files.add(line.split("=", 1)[1].strip())
    out = []
    for p in entries:
        if skip is not None and p.resolve() == skip:
            continue
        if p.is_dir():
            out.append(p)
        elif p.is_file() and p.suffix.lower() in FORMATS and p.name not in data_files:
            out.append(p)
    return out


def _names(paths: list[Path]) -> list[str]:
    """Output names: the file name without extension (folder name), made unique by the path relative to the
    inputs' common folder where two recordings share a name."""
    base = [p.name if p.is_dir() else p.stem for p in paths]
    if len(set(base)) == len(base):
        return base
    common = Path(os.path.commonpath([str(p.resolve()) for p in paths]))
    out = []
    for p, b in zip(paths, base):
        if base.count(b) > 1:
            rel = p.resolve().relative_to(common) if p.resolve() != common else Path(p.name)
            out.append("__".join(rel.parts[:-1] + (b,)))
        else:
            out.append(b)
    if len(set(out)) != len(out):
        dup = sorted({n for n in out if out.count(n) > 1})
        raise InputError(f"recordings with the same output name: {dup[:5]}; rename or run them separately")
    return out


def jobs_from_inputs(inputs, settings: dict | None = None, *, folders: str = "contents",
                     out_dir=None) -> list[Job]:
    """Jobs for ``inputs`` (files and folders), in a deterministic order.

    A file is one recording.  A folder is, with ``folders="contents"`` (default), a folder of recordings: each
    frame file in it and each sub-folder (a folder of per-frame files) is one; with ``folders="recording"`` the
    folder itself is one recording (per-frame files).  ``settings`` (see :func:`settings_keys`) apply to all;
    a recording's own settings file (:func:`settings_file_for`) overrides them for that recording.
    Raises :class:`InputError` for a missing input, an empty folder, an unknown or bad setting.
    """
    if folders not in ("contents", "recording"):
        raise InputError(f"folders must be 'contents' or 'recording', got {folders!r}")
    skip = Path(out_dir).resolve() if out_dir is not None else None
    paths: list[Path] = []
    groups: list[tuple[Path, list[Path]]] = []      # (input, its recordings) for the checks before any task runs
    for item in inputs:
        p = Path(item)
        if not p.exists():
            raise InputError(f"{p}: no such file or directory")
        if p.is_dir() and folders == "contents":
            found = _scan_folder(p, skip)
            if not found:
                raise InputError(f"{p}: no recordings in this folder (frame files or sub-folders)")
            paths += found
            groups.append((p, found))
        else:
            paths.append(p)
            groups.append((p, [p]))
    seen, unique = set(), []
    for p in paths:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    base = dict(settings or {})
    _check_settings({**default_settings(), **base}, "settings")
    jobs = []
    for p, name in zip(unique, _names(unique)):
        s = dict(base)
        sf = settings_file_for(p)
        if sf is not None:
            s.update(_read_settings_file(sf))
        job = Job(input=str(p.resolve()), name=name, settings=s)
        _check_settings(job.resolved(), str(sf or p))
        jobs.append(job)
    by_input = {j.input: j for j in jobs}
    for item, found in groups:
        _check_first_recordings(item, [by_input[str(f.resolve())] for f in found if str(f.resolve()) in by_input])
    return jobs


def _frames_needed(settings: dict) -> int:
    return 2 if settings["task"] == "track" else 1 + max(max(p) for p in settings["pairs"])


def _check_first_recordings(item: Path, jobs: list) -> None:
    """Bad input a batch can see before it runs, from the first readable recordings of one input: a folder
    whose files hold one frame each (the frames of one recording, read as recordings of their own), and
    frames that look transposed or a spacing that looks swapped (:mod:`femreg.orientation`).  Recordings that
    cannot be read are left to their tasks, which record the error."""
    from .io import read_frames
    from .orientation import OrientationError, check

    probed = []
    for job in jobs[:3]:
        try:
            reader_kw, _ = _check_settings(job.resolved(), job.input)
            probed.append((job, read_frames(job.input, **reader_kw)))
        except (InputError, OSError):
            continue
        if len(probed) == 2 or probed[0][1].n_frames > 1:
            break
    if not probed:
        return
    job, fr = probed[0]
    s = job.resolved()
    need = _frames_needed(s)
    if item.is_dir() and len(jobs) > 1 and all(f.n_frames == 1 for _, f in probed) and need > 1:
        what = "tracking needs 2" if s["task"] == "track" else f"pair {s['pairs'][0]} needs {need}"
        raise InputError(f"{item}: its {len(jobs)} files hold one frame each, and each file is a recording of its "
                         f"own ({what}); if they are the frames of one recording, pass --folders recording "
                         f"(folders='recording')")
    if not s.get("no_orientation_check"):
        try:
            check(fr.frames[0], fr.spacing)
        except OrientationError as exc:
            raise OrientationError(f"{job.input}: {exc}") from None


def _fingerprint(path: Path) -> list:
    """(name, size, mtime_ns) of the input's files: a changed input is a changed job."""
    files = sorted(f for f in path.iterdir() if f.is_file()) if path.is_dir() else [path]
    return [[f.name, f.stat().st_size, f.stat().st_mtime_ns] for f in files]


def _pair_id(pair) -> str:
    return f"pair_{int(pair[0]):03d}-{int(pair[1]):03d}"


def _task_specs(job: Job) -> list[dict]:
    """The tasks of a job: one per pair (register) or one (track); each a JSON-able dict."""
    s = job.resolved()
    fp = _fingerprint(Path(job.input))
    if s["task"] == "track":
        parts = [("track", None)]
        unused = ("pairs",)
    else:
        parts = [(_pair_id(p), [int(p[0]), int(p[1])]) for p in s["pairs"]]
        unused = ("pairs", "mode", "grid", "init")
    # The hash covers what changes a task's result (its own pair, not the job's other pairs) and the input.
    used = {k: v for k, v in s.items() if k not in unused}
    specs = []
    for tid, pair in parts:
        ident = json.dumps({"settings": used, "pair": pair, "input": fp}, sort_keys=True, default=str)
        specs.append({"key": f"{job.name}/{tid}", "name": job.name, "task_id": tid, "input": job.input,
                      "task": s["task"], "pair": pair, "settings": s,
                      "hash": hashlib.sha256(ident.encode()).hexdigest()[:16], "size": sum(f[1] for f in fp)})
    return specs


# ================================================================================================================
# The task of one recording (runs on a worker)
# ================================================================================================================

def _record_path(out_dir: Path, spec: dict) -> Path:
    return out_dir / spec["name"] / f"{spec['task_id']}.record.json"


def _read_record(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _reset_peak_rss() -> None:
    # Linux >= 4.0: writing 5 resets VmHWM, so the peak below is this task's, not the worker's lifetime peak.
    with contextlib.suppress(OSError):
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")


def _peak_rss_mb() -> float | None:
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    with contextlib.suppress(ImportError):
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return round(peak / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0), 1)
    return None


def run_recording_task(spec: dict, out_dir) -> dict:
    """Run one task of :func:`run_batch` (on a worker) and return its record; never raises for a failing
    recording (the record says ``status: "failed"`` with the error).  A task whose finished record is already
    on disk with the same settings returns it (``computed: False``): a task rescheduled after its worker died
    is not run twice."""
    out_dir = Path(out_dir)
    rpath = _record_path(out_dir, spec)
    old = _read_record(rpath)
    if old is not None and old.get("status") == "ok" and old.get("hash") == spec["hash"]:
        return {**old, "computed": False}
    folder = out_dir / spec["name"]
    folder.mkdir(parents=True, exist_ok=True)
    _reset_peak_rss()
    t0, c0 = time.perf_counter(), time.process_time()
    rec = {k: spec[k] for k in ("key", "name", "task_id", "input", "task", "pair", "hash")}
    rec.update(worker=f"{socket.gethostname()}:{os.getpid()}",
               blas_threads=os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS"))
    try:
        reader_kw, reg_kw = _check_settings(spec["settings"], spec["key"])
        rec.update(_run_track(spec, folder, reader_kw, reg_kw) if spec["task"] == "track"
                   else _run_pair(spec, folder, reader_kw, reg_kw))
        rec["status"], rec["error"] = "ok", None
    except Exception as exc:  # noqa: BLE001 - a failing recording is recorded; the batch goes on
        rec.update(status="failed", error=_describe_error(exc), traceback=traceback.format_exc(limit=20))
    rec["wall_s"] = round(time.perf_counter() - t0, 3)
    rec["cpu_s"] = round(time.process_time() - c0, 3)  # the worker process's CPU time: wall on a busy machine lies
    rec["peak_rss_mb"] = _peak_rss_mb()
    atomic_write_text(rpath, json.dumps(rec, indent=1, default=str))
    return {**rec, "computed": True}


def _quality(res, min_ncc) -> str:
    import math

    ok = math.isfinite(res.ncc_after) and res.ncc_after >= min_ncc
    return "" if ok else f"low NCC after registration ({res.ncc_after:.3f} < {min_ncc})"


def _run_pair(spec, folder: Path, reader_kw, reg_kw) -> dict:
    import numpy as np

    from .io import read_frames
    from .registration import register

    fr = read_frames(spec["input"], **reader_kw)
    i, j = spec["pair"]
    if max(i, j) >= fr.n_frames:
        hint = " (a folder of per-frame files is one recording with --folders recording)" if fr.n_frames == 1 else ""
        raise InputError(f"{spec['input']}: pair {i} {j} requested but it holds {fr.n_frames} frame(s){hint}")
    res = register(fr.frames[i], fr.frames[j], spacing=fr.spacing, origin=fr.origin, **reg_kw)
    flag = _quality(res, spec["settings"]["min_ncc"])
    out = folder / f"{spec['task_id']}.npz"
    atomic_savez(out, writer=lambda tmp: res.save(tmp, flag=np.str_(flag), pair=np.asarray([i, j], np.int64)))
    if not res.success:  # as `femreg register`: the result is written, and the pair counts as failed
        raise RuntimeError(f"registration failed: {res.message.removeprefix('FAILED: ')} (result kept in {out.name})")
    return {"output": str(out.relative_to(folder.parent)), "ncc_before": res.ncc_before,
            "ncc_after": res.ncc_after, "nit": int(res.nit), "success": bool(res.success), "flag": flag,
            "n_frames": 2}


def _run_track(spec, folder: Path, reader_kw, reg_kw) -> dict:
    from .io import read_frames
    from .sequence import track

    fr = read_frames(spec["input"], **reader_kw)
    if fr.n_frames < 2:
        raise InputError(f"{spec['input']}: holds {fr.n_frames} frame; tracking needs at least 2 frames (a "
                         f"folder of per-frame files is one recording with --folders recording)")
    s = spec["settings"]
    kw = dict(spacing=fr.spacing, origin=fr.origin, mode=s["mode"], grid=s["grid"], init=s["init"],
              checkpoint_dir=folder, min_ncc=s["min_ncc"], **reg_kw)
    # resume=True: a task rescheduled after its worker died continues from the last checkpointed frame.  The
    # client only reruns a task without a finished record, so frames of other settings are partial leftovers.
    try:
        out = track(fr.frames, resume=True, **kw)
    except InputError as exc:
        if "cannot resume" not in str(exc):
            raise
        for f in list(folder.glob("frame_*.npz")) + [folder / "track.json"]:
            f.unlink(missing_ok=True)
        out = track(fr.frames, resume=False, **kw)
    last = out[-1]
    return {"output": f"{folder.name}/", "ncc_before": last.ncc_before, "ncc_after": last.ncc_after,
            "nit": int(sum(r.nit for r in out)), "success": bool(all(r.success for r in out)),
            "flag": "; ".join(f"frame {k + 1}: {f}" for k, f in enumerate(out.flags) if f),
            "n_frames": len(out) + 1, "frames_resumed": int(sum(not c for c in out.computed))}


# ================================================================================================================
# run_batch
# ================================================================================================================

_COLUMNS = ("key", "status", "computed", "task", "n_frames", "ncc_before", "ncc_after", "nit", "success", "flag",
            "wall_s", "cpu_s", "peak_rss_mb", "worker", "output", "input", "error")


@dataclass
class BatchSummary:
    """The outcome of :func:`run_batch`: one record per task (sorted by key), and where the tables are.

    ``records[i]`` keys: key (``name/pair_III-JJJ`` or ``name/track``), status ("ok" | "failed"), computed
    (False: kept from an earlier run), ncc_before/ncc_after/nit/success/flag (registration quality), wall_s,
    cpu_s (CPU time of the worker process during the task), peak_rss_mb (peak resident memory of the worker process during the task, MiB), worker ("host:pid"),
    output (relative to ``out_dir``), input, error.
    """

    out_dir: Path
    records: list
    wall_s: float
    workers: str
    csv_path: Path | None = None
    md_path: Path | None = None

    @property
    def failed(self) -> list:
        return [r for r in self.records if r.get("status") != "ok"]

    @property
    def n_computed(self) -> int:
        return sum(1 for r in self.records if r.get("computed"))

    @property
    def ok(self) -> bool:
        return not self.failed

    def worker_memory(self) -> dict:
        """{worker: (tasks run, peak RSS MiB)} over the tasks computed in this run."""
        out: dict = {}
        for r in self.records:
            if r.get("computed") and r.get("worker"):
                n, m = out.get(r["worker"], (0, 0.0))
                out[r["worker"]] = (n + 1, max(m, r.get("peak_rss_mb") or 0.0))
        return out

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(_COLUMNS)
        for r in self.records:
            w.writerow([_cell(r.get(c), c) for c in _COLUMNS])
        return buf.getvalue()

    def to_markdown(self) -> str:
        cols = [c for c in _COLUMNS if c not in ("input", "worker")]
        lines = [f"# femreg batch: {len(self.records)} tasks, {len(self.failed)} failed, "
                 f"{self.n_computed} computed in this run",
                 "", f"Workers: {self.workers}; wall time {self.wall_s:.1f} s.", "",
                 "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in self.records:
            lines.append("| " + " | ".join(_cell(r.get(c), c).replace("|", "/") for c in cols) + " |")
        mem = self.worker_memory()
        if mem:
            lines += ["", "| worker | tasks | peak RSS (MiB) |", "|---|---|---|"]
            lines += [f"| {w} | {n} | {m:.0f} |" for w, (n, m) in sorted(mem.items())]
        return "\n".join(lines) + "\n"

    def __repr__(self) -> str:
        return (f"BatchSummary({len(self.records)} tasks, {len(self.failed)} failed, {self.n_computed} computed, "
                f"{self.wall_s:.1f} s, {self.out_dir})")


def _cell(v, col) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4f}" if col.startswith("ncc") else f"{v:.2f}" if col.endswith("_s") else f"{v:.4g}"
    return " ".join(str(v).split())


def _load_manifest(out_dir: Path) -> dict | None:
    p = out_dir / MANIFEST
    if not p.exists():
        return None
    m = _read_record(p)
    if not m or m.get("format") != _FORMAT:
        raise InputError(f"{p}: not a femreg batch manifest")
    return m


def run_batch(jobs, out_dir, *, client=None, workers: int = 2, scheduler: str | None = None,
              resume: bool = False, progress: bool = True, memory_limit="auto") -> BatchSummary:
    """Register or track every :class:`Job` into ``out_dir`` on Dask; returns the :class:`BatchSummary` (also
    written to ``out_dir/summary.csv`` and ``summary.md``).

    Parameters
    ----------
    jobs : list of Job
        E.g. from :func:`jobs_from_inputs`.  Names must be unique.
    out_dir : path
        Output folder; each task writes ``out_dir/<name>/...`` and its record, the manifest is ``batch.json``.
    client, workers, scheduler, memory_limit
        Where tasks run (:func:`run_tasks`): the given client, a scheduler address, or a LocalCluster of
        ``workers`` single-threaded processes; ``workers=0``: serially in this process.
    resume : bool
        Keep tasks finished by an earlier run in ``out_dir`` (their settings and inputs must be unchanged,
        otherwise :class:`InputError`); failed and missing tasks run.  Without it an ``out_dir`` that holds
        results is refused.
    """
    t0 = time.perf_counter()
    jobs = list(jobs)
    names = [j.name for j in jobs]
    if len(set(names)) != len(names):
        raise InputError(f"job names must be unique; repeated: {sorted({n for n in names if names.count(n) > 1})[:5]}")
    if client is None and (scheduler is not None or int(workers) > 0):  # before anything is written
        from .optional import require
        require("distributed", feature="femreg batch")
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot use {out_dir} as the output folder ({exc.strerror or exc})") from None
    specs = [sp for j in jobs for sp in _task_specs(j)]
    manifest = _load_manifest(out_dir)
    finished = {}
    if manifest is not None or any(out_dir.glob("*/*.record.json")):
        if not resume:
            raise InputError(f"{out_dir} already holds a batch; use resume=True (--resume) or another folder")
        changed = []
        for sp in specs:
            rec = _read_record(_record_path(out_dir, sp))
            if rec is None or rec.get("status") != "ok":
                continue
            if rec.get("hash") != sp["hash"]:
                old = (manifest or {}).get("tasks", {}).get(sp["key"], {})
                diff = sorted(k for k in set(old.get("settings", {})) | set(sp["settings"])
                              if old.get("settings", {}).get(k) != sp["settings"].get(k))
                changed.append(f"{sp['key']} ({', '.join(diff) if diff else 'input file changed'})")
            else:
                finished[sp["key"]] = {**rec, "computed": False}
        if changed:
            raise InputError(f"cannot resume in {out_dir}: settings or inputs changed for {len(changed)} finished "
                             f"task(s): {'; '.join(changed[:3])}; use another folder")
    tasks_meta = dict((manifest or {}).get("tasks", {}))
    tasks_meta.update({sp["key"]: {"input": sp["input"], "task": sp["task"], "pair": sp["pair"],
                                   "settings": sp["settings"], "hash": sp["hash"]} for sp in specs})
    from . import __version__

    atomic_write_text(out_dir / MANIFEST, json.dumps(
        {"format": _FORMAT, "femreg_version": __version__, "python": sys.version.split()[0],
         "updated_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "tasks": tasks_meta},
        indent=1, default=str))

    todo = [sp for sp in specs if sp["key"] not in finished]
    tasks = [Task(sp["key"], run_recording_task, (sp, str(out_dir.resolve())),
                  priority=int(sp["size"] // 1024) * (4 if sp["task"] == "track" else 1)) for sp in todo]
    workers_desc = "this process (serial)"

    def _go(cl):
        nonlocal workers_desc
        if cl is not None:
            info = cl.scheduler_info()
            ws = info.get("workers", {})
            workers_desc = (f"{len(ws)} Dask worker(s) at {info.get('address', '?')}, "
                            f"{sum(w.get('nthreads', 0) for w in ws.values())} thread(s)")
        return run_tasks(tasks, client=cl, workers=0, progress=progress, desc="batch")

    if client is not None:
        outcomes = _go(client)
    elif tasks:
        with open_client(min(int(workers), len(tasks)), scheduler, memory_limit=memory_limit) as cl:
            outcomes = _go(cl)
    else:
        outcomes = {}
    records = dict(finished)
    for sp in todo:
        oc = outcomes[sp["key"]]
        if oc.ok:
            records[sp["key"]] = oc.value
        else:  # the task never returned (its worker died too often): record it here
            rec = {k: sp[k] for k in ("key", "name", "task_id", "input", "task", "pair", "hash")}
            rec.update(status="failed", error=oc.error, computed=True)
            _record_path(out_dir, sp).parent.mkdir(parents=True, exist_ok=True)
            atomic_write_text(_record_path(out_dir, sp), json.dumps(rec, indent=1, default=str))
            records[sp["key"]] = rec
    ordered = [records[sp["key"]] for sp in sorted(specs, key=lambda s: s["key"])]
    summary = BatchSummary(out_dir=out_dir, records=ordered, wall_s=time.perf_counter() - t0, workers=workers_desc)
    summary.csv_path, summary.md_path = out_dir / "summary.csv", out_dir / "summary.md"
    atomic_write_text(summary.csv_path, summary.to_csv())
    atomic_write_text(summary.md_path, summary.to_markdown())
    return summary
