"""Atomic file writes (temporary file in the same folder + rename): an interrupted run never leaves a
half-written result that a resume would trust."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _tmp(path: Path, suffix: str) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")


def atomic_write_text(path, text: str) -> None:
    path = Path(path)
    tmp = _tmp(path, "")
    tmp.write_text(text)
    os.replace(tmp, path)


def atomic_savez(path, writer=None, **arrays) -> None:
    """``np.savez_compressed(path, **arrays)`` atomically; or ``writer(tmp_path)`` writes the .npz itself."""
    path = Path(path)
    tmp = _tmp(path, ".npz")
    if writer is not None:
        writer(tmp)
    else:
        np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


#: Entries of a run's record that follow from its settings (the mesh a spacing makes, the region it registers):
#: a resume refused names the settings that differ first.
DERIVED = ("n_nodes", "mesh_checksum", "roi")


def open_run_folder(folder, params: dict, *, resume: bool, record: str, started, kind: str,
                    argument: str = "output_dir", reselect=(), on_reselect=None, described=None):
    """The output folder of a resumable run (``track``, ``elastogram``): create it, refuse a resume whose
    parameters differ from those recorded in ``folder/record`` (JSON), refuse to start over a run already there
    without ``resume`` (``started``: glob patterns of the files a run writes), then record ``params``.

    ``reselect``: names of parameters that only select among what the run computes first (an elastogram's band):
    a resume may change them; ``on_reselect(names)`` is then called with those that changed, so that the caller
    drops what depended on them.  ``described``: entries written to the record beside ``params`` but not
    compared on resume (what the run is, e.g. the frames' shape beside the registered region's: a folder written
    before they were recorded still resumes).

    Returns the folder as a Path, or None when ``folder`` is None (``resume`` then needs a folder: InputError
    naming ``argument``)."""
    import json

    from .errors import InputError, pass_as

    if folder is None:
        if resume:
            raise InputError(f"resume=True needs {argument}")
        return None
    out = Path(folder)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot use {out} as the output folder ({exc.strerror or exc})") from None
    pfile = out / record
    if pfile.exists() and resume:
        old = json.loads(pfile.read_text())
        diff = [k for k in params if old.get(k) != params[k]]
        fixed = [k for k in diff if k not in reselect]
        if fixed:
            # what follows from the settings (the mesh, the region) is named after them, not as something to pass
            given = [k for k in fixed if k not in DERIVED] or fixed
            was = "; ".join(f"{k}: {old.get(k)!r} recorded, {params[k]!r} now" for k in given)
            if len(given) < len(fixed):
                was += f" (and with it {', '.join(k for k in fixed if k not in given)})"
            raise InputError(f"cannot resume from {out}: parameters differ ({was}); pass the recorded ones, or "
                             f"start over in another folder")
        if diff and on_reselect is not None:
            on_reselect(diff)
    elif not resume and any(any(out.glob(p)) for p in started):
        raise InputError(f"{out} already holds {kind}; use "
                         + pass_as("resume=True (--resume)", "--resume") + " or another folder")
    atomic_write_text(pfile, json.dumps({**params, **(described or {})}, indent=1))
    return out


def save_frame(path, result, increment, flag: str, k: int, mode: str, retried: str = "") -> None:
    """Write a tracking run's frame ``k`` (frame 0 -> k) atomically: ``result.save`` with the increment of eq:IR,
    the flag ('' or why it is flagged), the frame index and the run's mode; ``retried`` ('' or why the increment
    was registered again from a fresh start), written only when not empty."""
    extra = dict(retried=np.str_(retried)) if retried else {}
    atomic_savez(path, writer=lambda tmp: result.save(tmp, increment=increment, flag=np.str_(flag),
                                                      frame=np.int64(k), mode=np.str_(mode), **extra))


def load_frame_record(path) -> tuple:
    """``(increment, flag, retried)`` of a frame file written by :func:`save_frame`: ``retried`` why the increment
    was registered again from a fresh start ('' when it was not; files written before retries were recorded read
    '')."""
    with np.load(path, allow_pickle=False) as z:
        return (np.asarray(z["increment"], float), str(z["flag"]),
                str(z["retried"]) if "retried" in z.files else "")


def progress_bar(progress: bool, total: int, desc: str, unit: str, on_item=None):
    """A progress bar for a tracking run (:func:`femreg.progress.bar`: tqdm on a terminal, plain lines
    otherwise), or None without ``progress``.  ``on_item``: the run's per-item callback; when it has a true
    ``reports_progress`` attribute it prints a line per item itself, so off a terminal there is no bar (one line
    per item, not those lines and the bar's as well)."""
    if not progress:
        return None
    from .progress import bar, stderr_is_terminal

    if getattr(on_item, "reports_progress", False) and not stderr_is_terminal():
        return None

    return bar(total=total, desc=desc, unit=unit)
