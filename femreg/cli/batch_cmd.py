"""``femreg batch INPUT [INPUT ...] -o OUT/``: register or track many recordings in parallel on Dask.

INPUTS are frame files and folders (a folder's frame files and sub-folders are its recordings; with
``--folders recording`` a folder is one recording of per-frame files).  One task per recording (``--task track``,
default) or per frame pair (``--task register --pair I J``, repeatable), on a local cluster of ``--workers``
processes (one BLAS thread each) or on a running Dask scheduler (``--scheduler tcp://host:8786``).  Results go to
``OUT/<recording>/`` as each task finishes (``frame_KKK.npz`` + ``track.json`` as ``femreg track`` writes them,
or ``pair_III-JJJ.npz`` as ``femreg register``); ``OUT/summary.csv`` and ``OUT/summary.md`` list every task.

Per-recording settings: ``NAME.femreg.toml`` (or ``.json``) beside the recording, or ``femreg.toml`` inside a
folder recording, with the flags' long names as keys (``regularizer = "strain"``, ``spacing = [0.02, 0.3]``,
``pair = [0, 3]``, ``frames = "0:10"``); they override the command line for that recording.

Exit codes: 0 all tasks done and none flagged; 1 some task failed or was flagged (low NCC, a frame whose
registration failed its check; the others finished; the summary names the error; ``--resume`` reruns the failed
ones only); 2 bad input, found before anything runs (a missing input, bad settings, a folder of single-frame
files without ``--folders recording``, an input that is one recording and cannot be read, frames that look
transposed or a swapped spacing in any recording, each checked on its first frame).
"""
from __future__ import annotations

import sys

from ._common import add_reader_args, add_registration_args, ncc_arg


def add_parser(subparsers):
    p = subparsers.add_parser(
        "batch", help="register or track many recordings in parallel (Dask: local processes or a cluster)",
        description="Register or track every recording of INPUTS on Dask, one task per recording (or per frame "
                    "pair with --task register), each result written atomically to OUT/<recording>/ as it "
                    "finishes; a failing recording is recorded with its error and the others go on; "
                    "OUT/summary.csv and OUT/summary.md list every task.  --resume keeps finished tasks "
                    "(settings must be unchanged).  Per-recording settings: NAME.femreg.toml or NAME.femreg.json "
                    "beside the recording, keys as the long flag names.")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="frame files, folders of recordings, or (--folders recording) folders of per-frame files")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output folder")
    p.add_argument("--task", choices=("track", "register"), default="track",
                   help="track every frame to the first (default), or register frame pairs (--pair)")
    p.add_argument("--pair", metavar=("I", "J"), type=int, nargs=2, action="append",
                   help="--task register: reference and moving frame indices (repeat for several pairs, one "
                        "task each; default 0 1)")
    p.add_argument("--mode", choices=("accumulate", "direct"), default="accumulate",
                   help="track: accumulate (default): register each frame to the one before and sum the increments in "
                        "first-frame coordinates (eq:IR); direct: register frame 0 to each frame")
    p.add_argument("--grid", choices=("current", "reference"), default="current",
                   help="track: pixel grid of accumulation (see femreg track --help)")
    p.add_argument("--init", choices=("previous", "blockmatch"), default="previous",
                   help="track: initial guess of each increment")
    p.add_argument("--min-ncc", type=ncc_arg, default=0.5, help="flag pairs whose NCC after is below (default 0.5)")
    p.add_argument("--folders", choices=("contents", "recording"), default="contents",
                   help="an INPUT folder holds recordings (default), or is one recording of per-frame files")
    g = p.add_argument_group("where the tasks run")
    g.add_argument("--workers", type=int, default=2, metavar="N",
                   help="local worker processes, one thread each (default 2; 0 = serially in this process)")
    g.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786, or its scheduler file .json) instead of a "
                        "local cluster; the workers must see INPUTS and OUT at the same paths")
    g.add_argument("--memory-limit", default="auto", metavar="BYTES",
                   help="local workers: memory per worker, e.g. 4GB (default: the machine's memory / N)")
    p.add_argument("--resume", action="store_true", help="keep the finished tasks of an earlier run in OUT")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_registration_args(p)
    add_reader_args(p)
    p.set_defaults(func=run)
    return p


def settings_from_args(args) -> dict:
    """The batch settings (femreg.batch.settings_keys()) given on the command line."""
    from ..batch import flag_defaults, frames_text

    reg, reader = flag_defaults()
    s = {k: getattr(args, k) for k in list(reg) + list(reader)}
    s["frames"] = frames_text(s["frames"])
    s.update(task=args.task, pairs=[list(p) for p in (args.pair or [[0, 1]])], mode=args.mode, grid=args.grid,
             init=args.init, min_ncc=args.min_ncc)
    return s


def run(args) -> int:
    from ..batch import jobs_from_inputs, run_batch
    from ..errors import InputError

    if args.pair and args.task != "register":
        raise InputError("--pair applies to --task register")
    if args.scheduler is None and args.workers < 0:
        raise InputError(f"--workers must be >= 0, got {args.workers}")
    jobs = jobs_from_inputs(args.inputs, settings_from_args(args), folders=args.folders, out_dir=args.output,
                            refuse_unreadable=True)
    summary = run_batch(jobs, args.output, workers=args.workers, scheduler=args.scheduler, resume=args.resume,
                        progress=not args.no_progress, memory_limit=args.memory_limit)
    n = len(summary.records)
    for r in summary.failed:
        print(f"femreg batch: FAILED {r['key']}: {r.get('error')}", file=sys.stderr)
    flagged = [r for r in summary.records if r.get("flag") and r.get("status") == "ok"]
    for r in flagged:
        print(f"femreg batch: FLAGGED {r['key']}: {r['flag']}", file=sys.stderr)
    n_flag = len(flagged)
    mem = summary.worker_memory()
    peak = max((m for _, m in mem.values()), default=None)
    print(f"femreg batch: {n} task(s) in {args.output} ({summary.n_computed} computed, "
          f"{n - summary.n_computed} kept, {len(summary.failed)} failed, {n_flag} flagged) in "
          f"{summary.wall_s:.1f} s on {summary.workers}"
          + (f"; peak worker memory {peak:.0f} MiB" if peak else ""))
    print(f"summary: {summary.md_path}")
    return 0 if summary.ok and not n_flag else 1
