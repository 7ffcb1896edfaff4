"""Running :mod:`femreg.batch`: the tasks of the jobs (one per registered pair, or one track), each run on a worker
(:func:`run_recording_task`: reads its input, writes its result and then its record atomically), and
:func:`run_batch`, which schedules them on the engine, keeps finished ones on ``resume`` and writes the manifest and
the summary.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import sys
import time
import traceback
from pathlib import Path

from .._atomic import atomic_savez, atomic_write_text
from ..errors import InputError, cli_wording, cli_wording_on, pass_as
from .engine import Task, _describe_error, open_client, run_tasks
from .inputs import Job, pair_beyond, settings_file_for
from .settings import _check_settings
from .summary import BatchSummary

#: The manifest file of a batch folder.
MANIFEST = "batch.json"
_FORMAT = "femreg-batch 1"

__all__ = ["run_batch", "run_recording_task", "MANIFEST"]


def _fingerprint(path: Path) -> list:
    """(name, size, mtime_ns) of the input's files: a changed input is a changed job."""
    files = sorted(f for f in path.iterdir() if f.is_file()) if path.is_dir() else [path]
    return [[f.name, f.stat().st_size, f.stat().st_mtime_ns] for f in files]


def _pair_id(pair) -> str:
    return f"pair_{int(pair[0]):03d}-{int(pair[1]):03d}"


#: Settings added after batches were first written (transpose; the IQ flags --iq-frequency, --iq-conjugate).
_LATER_FLAGS = ("transpose", "modulation_frequency", "iq_conjugate")


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
    # flags added later are left out at their defaults, so the tasks of runs from before they existed still match
    # on --resume
    used = {k: v for k, v in s.items() if k not in unused and not (k in _LATER_FLAGS and not v)}
    specs = []
    for tid, pair in parts:
        ident = json.dumps({"settings": used, "pair": pair, "input": fp}, sort_keys=True, default=str)
        specs.append({"key": f"{job.name}/{tid}", "name": job.name, "task_id": tid, "input": job.input,
                      "task": s["task"], "pair": pair, "settings": s,
                      "hash": hashlib.sha256(ident.encode()).hexdigest()[:16], "size": sum(f[1] for f in fp)})
    return specs


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
    with cli_wording() if spec.get("cli") else contextlib.nullcontext():
        try:
            reader_kw, reg_kw = _check_settings(spec["settings"], spec["key"])
            rec.update(_run_track(spec, folder, reader_kw, reg_kw) if spec["task"] == "track"
                       else _run_pair(spec, folder, reader_kw, reg_kw))
            rec["status"], rec["error"] = "ok", None
        except Exception as exc:  # noqa: BLE001 - a failing recording is recorded; the batch goes on
            rec.update(status="failed", error=_task_error(exc, spec), traceback=traceback.format_exc(limit=20))
    rec["wall_s"] = round(time.perf_counter() - t0, 3)
    rec["cpu_s"] = round(time.process_time() - c0, 3)  # the worker process's CPU time: wall on a busy machine lies
    rec["peak_rss_mb"] = _peak_rss_mb()
    atomic_write_text(rpath, json.dumps(rec, indent=1, default=str))
    return {**rec, "computed": True}


def _task_error(exc, spec) -> str:
    """The error of a failed task as its record keeps it: the exception's class and message; on the command line
    bad input reads "bad input: ..." and names the recording's settings file, whose values override the flags."""
    if not (spec.get("cli") and isinstance(exc, InputError)):
        return _describe_error(exc)
    msg = " ".join(str(exc).split())
    try:
        sf = settings_file_for(spec["input"])
    except InputError:
        sf = None
    where = f" ({sf.name} beside the recording sets its own settings, which override the command line)" if sf else ""
    return f"bad input: {msg}{where}"


def _quality(res, min_ncc) -> str:
    import math

    ok = math.isfinite(res.ncc_after) and res.ncc_after >= min_ncc
    return "" if ok else f"low NCC after registration ({res.ncc_after:.3f} < {min_ncc})"


def _run_pair(spec, folder: Path, reader_kw, reg_kw) -> dict:
    import numpy as np

    from ..io import read_frames
    from ..registration import register

    fr = read_frames(spec["input"], **reader_kw)
    i, j = spec["pair"]
    why = pair_beyond((i, j), fr.n_frames)
    if why:
        hint = " (a folder of per-frame files is one recording with --folders recording)" if fr.n_frames == 1 else ""
        raise InputError(f"{spec['input']}: {why}{hint}")
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
    from ..io import read_frames
    from ..repair import summarise_flags
    from ..sequence import track

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
            "flag": summarise_flags(out.flags),
            "n_frames": len(out) + 1, "frames_resumed": int(sum(not c for c in out.computed))}


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
        from ..optional import require
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
            raise InputError(f"{out_dir} already holds a batch; use "
                             + pass_as("resume=True (--resume)", "--resume") + " or another folder")
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
    from .. import __version__

    atomic_write_text(out_dir / MANIFEST, json.dumps(
        {"format": _FORMAT, "femreg_version": __version__, "python": sys.version.split()[0],
         "updated_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "tasks": tasks_meta},
        indent=1, default=str))

    todo = [sp for sp in specs if sp["key"] not in finished]
    # the command line's wording travels with the tasks (their messages name flags, not Python arguments)
    wording = {"cli": True} if cli_wording_on() else {}
    tasks = [Task(sp["key"], run_recording_task, ({**sp, **wording}, str(out_dir.resolve())),
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
