"""Inputs of :mod:`femreg.batch`: the recordings (:class:`Job`: a frame file or a folder of frame files, its output
name and settings) from files and folders, with their per-recording settings files.
"""
from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError, pass_as
from .settings import _check_settings, default_settings

__all__ = ["Job", "jobs_from_inputs", "settings_file_for"]


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
        elif key == "iq_frequency":  # the flag's name; its setting is read_frames' argument
            key = "modulation_frequency"
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
    order; MetaImage data files (the .raw of a .mhd), femreg's own result files (set aside as
    :func:`femreg.io.read_frames` sets them aside in a folder of frames) and hidden entries are left out."""
    from ..io.readers import FORMATS, is_result_file, natural_key

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
        elif p.is_file() and p.suffix.lower() in FORMATS and p.name not in data_files and not is_result_file(p):
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
                     out_dir=None, refuse_unreadable: bool = False) -> list[Job]:
    """Jobs for ``inputs`` (files and folders), in a deterministic order.

    A file is one recording.  A folder is, with ``folders="contents"`` (default), a folder of recordings: each
    frame file in it and each sub-folder (a folder of per-frame files) is one; with ``folders="recording"`` the
    folder itself is one recording (per-frame files).  ``settings`` (see :func:`settings_keys`) apply to all;
    a recording's own settings file (:func:`settings_file_for`) overrides them for that recording.
    Raises :class:`InputError` for a missing input, an empty folder, an unknown or bad setting, and with
    ``refuse_unreadable`` (the command line) for an input that is one recording and cannot be read.
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
        _check_first_recordings(item, [by_input[str(f.resolve())] for f in found if str(f.resolve()) in by_input],
                                refuse_unreadable)
    return jobs


def pair_beyond(pair, n_frames: int) -> str:
    """Why the frame ``pair`` (I, J) cannot be taken from a recording of ``n_frames`` frames, in the words of
    ``femreg register --pair``; "" when it can."""
    bad = [int(k) for k in pair if not 0 <= int(k) < n_frames]
    if not bad:
        return ""
    return (f"--pair {pair[0]} {pair[1]}: no frame {bad[0]}: the recording holds {n_frames} frame(s), counted "
            f"from 0: 0 to {n_frames - 1}")


def _frames_needed(settings: dict) -> int:
    return 2 if settings["task"] == "track" else 1 + max(max(p) for p in settings["pairs"])


def _check_first_recordings(item: Path, jobs: list, refuse_unreadable: bool = False) -> None:
    """Bad input a batch can see before it runs, from the first readable recordings of one input: a folder
    whose files hold one frame each (the frames of one recording, read as recordings of their own), and, from
    each recording's first frame, frames that look transposed or a spacing that looks swapped
    (:mod:`femreg.orientation`).  With
    ``refuse_unreadable``, an input that is one recording and cannot be read is refused, and so is a folder whose
    recordings lack a setting (a raw file without --shape, no spacing); otherwise, and for a corrupt file in a
    folder of several, recordings that cannot be read are left to their tasks, which record the error."""
    from ..errors import FileFormatError
    from ..io import read_frames
    from ..orientation import OrientationError

    probed = []
    for job in jobs[:3]:
        try:
            reader_kw, _ = _check_settings(job.resolved(), job.input)
            probed.append((job, read_frames(job.input, **reader_kw)))
        except (InputError, OSError) as exc:
            if isinstance(exc, OrientationError) and exc.problem == "sampling":
                raise _named(job, exc) from None   # a spacing against the file's sampling rate: before any work
            if refuse_unreadable and len(jobs) == 1 and isinstance(exc, InputError):   # nothing else would run
                raise
            if refuse_unreadable and isinstance(exc, InputError) and not isinstance(exc, FileFormatError):
                raise       # a setting every recording lacks (--shape, --spacing), not one corrupt file
            if refuse_unreadable and len(jobs) == 1:
                raise InputError(f"{job.input}: {exc}") from None
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
                         f"own ({what}); if they are the frames of one recording, pass "
                         + pass_as("--folders recording (folders='recording')", "--folders recording"))
    import numpy as np

    from ..mesh import check_element_size

    es = s.get("element_size")
    try:        # an element size in metres: every task would mesh one pixel per element
        check_element_size(None if es is None else np.ravel(np.asarray(es, float)), fr.spacing)
    except InputError as exc:
        raise InputError(f"{job.input}: {exc}") from None
    if len(jobs) == 1 and s["task"] == "register":
        # one recording: a pair beyond its last frame (often counted from 1) fails every task of it
        for pair in s["pairs"]:
            why = pair_beyond(pair, fr.n_frames)
            if why:
                raise InputError(f"{job.input}: {why}")
    _check_orientation(job, fr)
    for other in jobs:          # each recording's first frame: one transposed file among many fails only its tasks
        if other is job or other.resolved().get("no_orientation_check"):
            continue
        try:
            reader_kw, _ = _check_settings(other.resolved(), other.input)
            first = read_frames(other.input, **{**reader_kw, "frames": slice(0, 1)})
        except (InputError, OSError) as exc:
            if isinstance(exc, OrientationError) and exc.problem == "sampling":
                raise _named(other, exc) from None   # a spacing against the file's sampling rate
            continue            # unreadable: left to its tasks, which record the error
        _check_orientation(other, first)


def _check_orientation(job, fr) -> None:
    """:class:`OrientationError` naming ``job``'s recording when its frames ``fr`` look transposed or its spacing
    swapped (:mod:`femreg.orientation`); nothing when its settings turn the check off."""
    from ..orientation import OrientationError, check, check_raw_shape

    if job.resolved().get("no_orientation_check"):
        return
    try:
        check_raw_shape(fr)
        # a file's whole frame: its size counts too (a spacing in cm)
        check(fr.frames[0], fr.spacing, whole_frame=fr.frames.ndim == 3)
    except OrientationError as exc:
        raise _named(job, exc) from None


def _named(job, exc):
    """The :class:`OrientationError` ``exc`` of ``job``'s recording, naming it and the settings file beside it
    (whose settings override the command line); a transposed refusal of frames already read with ``transpose``
    says to leave it out."""
    from ..orientation import OrientationError, transposed_as_told

    msg, p = str(exc), Path(job.input)
    sf = settings_file_for(p)
    if job.resolved().get("transpose"):
        own = sf or p.with_name(f"{p.name if p.is_dir() else p.stem}.femreg.toml")
        msg = transposed_as_told(msg, f"for this recording ({own.name} beside it: transpose = false)")
    if sf is not None and sf.name not in msg:
        msg += f" ({sf.name} beside the recording sets its own settings, which override the command line)"
    if not msg.startswith(f"{job.input}: ") and not msg.startswith(f"{Path(job.input)}: "):
        msg = f"{job.input}: {msg}"
    return OrientationError(msg, problem=exc.problem)
