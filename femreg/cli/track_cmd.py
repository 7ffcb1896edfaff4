"""``femreg track FILE -o OUTDIR``: displacement from the first frame to every later frame (eq:IR), with a
progress bar, one checkpoint file per frame as soon as it is done, and ``--resume``.  ``--geometry convex|sector``
(``--radius``, ``--angle-pitch``): frames along the rays of a convex / phased array, results in physical x, y
(:mod:`femreg.geometry`); only the range step of the spacing is read (``--spacing DX auto``).

Exit codes: 0 every frame registered; 1 a frame was flagged (its registration failed its own check, or its NCC
after is below ``--min-ncc``; every frame is still written and the flagged ones are listed) or a frame could not
be computed (the message names it; the frames before it are kept on disk and ``--resume`` continues); 2 bad
input, found before any frame is registered.
"""
from __future__ import annotations

from ..errors import InputError
from ._common import (add_reader_args, add_registration_args, add_volume_arg, beam_frames_from_args,
                      frames_from_args, ncc_arg, registration_kwargs, run_tracking)
from .register_cmd import (_check_stated_geometry, _geometry, _refuse_curved, _swept, add_geometry_args,
                           beam_start_range, refuse_unused_geometry)


def add_parser(subparsers):
    p = subparsers.add_parser(
        "track", help="track a frame sequence (accumulated or direct), checkpointing every frame",
        description="Register every frame of FILE to the first one.  'accumulate' (default) sums the increments "
                    "between consecutive frames in first-frame coordinates (eq:IR); 'direct' registers frame 0 "
                    "to frame k.  Each frame's result is written to OUTDIR/frame_KKK.npz when it finishes; "
                    "--resume continues an interrupted run without recomputing finished frames.  Pairs whose "
                    "NCC after registration is below --min-ncc are flagged, the run continues and the command "
                    "exits with code 1 listing them.  If a frame cannot be computed, the frames before it stay "
                    "saved, the command exits with code 1 naming the frame, and --resume continues from there.  "
                    "Bad input: exit 2 before any frame is registered.  Volumes (.npz with a spacing of 3 values) "
                    "are tracked the same way; --geometry swept for a swept probe's volumes, all scan-converted "
                    "onto one Cartesian grid.  --geometry convex / sector: frames (samples, rays) of a convex or "
                    "phased array, tracked in physical x, y (--radius, --angle-pitch; only the range step of "
                    "--spacing is read: --spacing DX auto).")
    p.add_argument("file", help="RF or B-mode frames (npy, npz, mat, mhd, raw, Clarius raw, .rf, .uff/.h5, DICOM .dcm, "
                                "or a folder of per-frame files)")
    p.add_argument("-o", "--output", required=True, metavar="OUTDIR", help="folder for frame_KKK.npz results")
    p.add_argument("--mode", choices=("accumulate", "direct"), default="accumulate",
                   help="accumulate (default): register each frame to the one before and sum the increments in "
                        "first-frame coordinates (eq:IR); direct: register frame 0 to each frame")
    p.add_argument("--grid", choices=("current", "reference"), default="current",
                   help="accumulation: register on each frame's pixel grid with the mesh moved by the accumulated "
                        "field (default), or on the first frame's grid as eq:IR is written (biased on noisy data)")
    p.add_argument("--init", choices=("previous", "blockmatch"), default="previous",
                   help="initial guess of each increment: the previous increment (default; a compression "
                        "sequence's increments are alike; one flagged from it is registered again afresh) or block "
                        "matching (each afresh: a freehand loop whose compression per frame varies)")
    p.add_argument("--resume", action="store_true", help="continue a run in OUTDIR, keeping finished frames")
    p.add_argument("--min-ncc", type=ncc_arg, default=0.5, help="flag pairs whose NCC after is below (default 0.5)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_volume_arg(p)
    add_geometry_args(p)
    add_registration_args(p)
    add_reader_args(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from ..sequence import track

    from ._volume import read_volume_file, track_volumes
    vol = read_volume_file(args.file, volume=args.volume, origin=getattr(args, "origin", None),
                           spacing=getattr(args, "spacing", None), variable=getattr(args, "variable", None),
                           check_sampling=not getattr(args, "no_orientation_check", False))
    kw = registration_kwargs(args)
    refuse_unused_geometry(args)
    if vol is not None:                 # a volume sequence (spacing with 3 values)
        if getattr(args, "transpose", False):
            raise InputError("--transpose is for frames (lines x samples); transpose a volume's axes before "
                             "saving it (axial, lateral, elevational)")
        if args.geometry in ("convex", "sector"):
            raise InputError(f"--geometry {args.geometry} is for frames; a swept probe's volumes take --geometry "
                             "swept")
        if args.geometry == "swept":    # a swept probe's volumes (femreg.swept)
            kw["geometry"] = _swept(args)
        return track_volumes(args, vol, kw)
    if args.geometry == "swept":
        raise InputError(f"--geometry swept needs a volume-sequence file (spacing of 3 values, or --volume), got "
                         f"{args.file}")
    if args.geometry in ("convex", "sector"):   # frames along rays: range step and first range from the file
        kw["geometry"] = _geometry(args)
        fr, spacing, origin = beam_frames_from_args(args, kw["geometry"])
        _check_stated_geometry(fr, args.file, kw["geometry"], args)
        origin = (beam_start_range(fr, args.file, args), 0.0)
    else:
        fr = frames_from_args(args)
        if not getattr(args, "geometry_given", False):
            _refuse_curved(fr, args.file)
        spacing, origin = fr.spacing, fr.origin
    if fr.n_frames < 2:     # the file named, and where the other frames may be
        raise InputError(f"{args.file}: one frame read: tracking needs at least 2 frames (a file of several "
                         f"frames, a folder of per-frame files: femreg track FOLDER, or --frames selecting 2 or "
                         f"more)")
    return run_tracking(args, lambda on_frame: track(
        fr.frames, spacing=spacing, origin=origin, mode=args.mode, grid=args.grid, init=args.init,
        checkpoint_dir=args.output, resume=args.resume, progress=not args.no_progress, min_ncc=args.min_ncc,
        on_frame=on_frame, **kw), "frame", total=fr.n_frames - 1)
