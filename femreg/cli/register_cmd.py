"""``femreg register REF [MOVING] -o OUT.npz``: two-frame registration of RF frames from any supported file.

REF and MOVING are read with :func:`femreg.io.read_frames` (npy/npz with ``rf`` and ``spacing``, mat, mhd, raw,
Ultrasonix .rf, Clarius raw, a folder of frame files).  With one file, ``--pair I J`` picks the two frames
(default 0 1).
OUT is written by :meth:`femreg.RegistrationResult.save` (mesh, nodal u, ux/uy/exx/eyy/exy on the pixel grid).
A pair whose NCC after registration is below ``--min-ncc`` is flagged (message, result still written).

Exit codes: 0 registered; 1 the registration failed (``success=False``: the images do not match, the result
would be worse than its start, peak hopping could not be repaired, or a numerical failure) or was flagged (NCC
after below ``--min-ncc``) -- the result file is still written when there is one, with ``success`` and the
message; 2 bad input (unreadable file, frames that look transposed or a spacing that looks swapped, ...), found
before any registration.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ._common import (add_reader_args, add_registration_args, add_volume_arg, beam_spacing_args, beam_spacing_error,
                      frames_from_args, ncc_arg, registration_kwargs)


def add_parser(subparsers):
    p = subparsers.add_parser(
        "register", help="register two frames (any supported file format)",
        description="Two-frame FE registration, reference(x) ~ moving(x + u(x)).  Writes mesh, nodal u and ux, uy, "
                    "exx, eyy, exy on the reference pixel grid to OUT.npz (femreg plot OUT.npz draws it).")
    p.add_argument("reference", help="reference frame file (or a multi-frame file with --pair)")
    p.add_argument("moving", nargs="?", help="moving frame file (omit to take both frames from REFERENCE)")
    p.add_argument("--pair", metavar=("I", "J"), type=int, nargs=2,
                   help="frame indices of reference and moving in multi-frame files, counted from 0 (default 0 1, or 0 0 with two "
                        "single-frame files)")
    p.add_argument("-o", "--output", required=True, help="output .npz (missing folders are created)")
    add_volume_arg(p)
    p.add_argument("--min-ncc", type=ncc_arg, default=0.5, help="flag the pair if NCC after is below (default 0.5)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bar (shown over the candidate registrations of --alpha auto)")
    add_geometry_args(p)
    g = p.add_argument_group("adaptive refinement (femreg.refine)")
    g.add_argument("--refine", metavar="N|auto|slip|none", default=None,
                   help="refine the mesh where the jumps of A[u] stand out and solve again: N passes, auto (one "
                        "pass quartering the marked rows / columns: femreg.refine.DEEP_REFINEMENT), slip (3 "
                        "passes, and the shear-traction weight lowered where layers slide; "
                        "femreg.refine.SLIP_REFINEMENT), none (or 0) off; default auto with --strategy auto and "
                        "R_P_sigma on the default mesh, off otherwise")
    add_registration_args(p)
    add_reader_args(p)
    p.set_defaults(func=run)
    return p


class _Given(argparse.Action):
    """Store the value and record that the flag was given (``geometry_given``): a file whose header states a
    curved array is refused only when no geometry was chosen."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.geometry_given = True


def add_geometry_args(p, choices=("linear", "convex", "sector", "swept")):
    """The probe geometry options (``--geometry`` of ``choices``, and each geometry's parameters; the swept
    probe's only when ``choices`` holds it)."""
    g = p.add_argument_group("probe geometry (femreg.geometry)")
    swept = "swept" in choices
    g.add_argument("--geometry", choices=choices, default="linear", action=_Given,
                   help=("frames sampled along the rays of a convex or phased (sector) array: (samples, rays), the "
                         "axial spacing is the range step, registered in physical x, y (default linear)"
                         if "convex" in choices else "default linear")
                   + ("; swept: volumes (samples, lines, frames) of a mechanically swept probe, the file's spacing "
                      "(range step mm, line pitch mm or deg, frame step deg), registered in physical x, y, z "
                      "(femreg.swept)" if swept else ""))
    g.add_argument("--radius", type=float, metavar="MM",
                   help="convex: apex distance behind the face, mm" if "convex" in choices
                   else "swept convex array: apex distance behind the face, mm")
    g.add_argument("--angle-pitch", type=float, metavar="DEG",
                   help="convex / sector: angle between rays, deg" if "convex" in choices
                   else "swept convex / sector array: angle between rays, deg")
    if not swept:
        return
    g.add_argument("--sweep-radius", type=float, metavar="MM",
                   help="swept: distance of the sweep axis behind the face, mm (0: on the face); the array is "
                        "linear, or convex / sector with --radius / --angle-pitch")
    g.add_argument("--angle-step", type=float, metavar="DEG", help="swept: angle between frames, deg")


def _frame(fr, index, path):
    from ._common import frame_index

    return fr.frames[frame_index(index, fr.n_frames, path, "--pair")]


def _swept(args):
    import femreg
    from femreg.errors import InputError

    if args.sweep_radius is None or args.angle_step is None:
        raise InputError("--geometry swept needs --sweep-radius (mm from the sweep axis to the face) and "
                         "--angle-step (degrees between frames)")
    array = None
    if args.angle_pitch is not None:
        array = femreg.Convex(args.radius, args.angle_pitch) if args.radius else femreg.Sector(
            angle_pitch_deg=args.angle_pitch)
    elif args.radius is not None:
        raise InputError("a swept convex array needs --angle-pitch with --radius")
    return femreg.Swept(sweep_radius_mm=args.sweep_radius, angle_step_deg=args.angle_step, array=array)


def refuse_unused_geometry(args) -> None:
    """A probe's parameters given without ``--geometry`` would be ignored (the frames registered as a linear
    array's): :class:`femreg.errors.InputError` naming the geometry they belong to."""
    from femreg.errors import InputError

    if args.geometry != "linear":
        return
    given = [f for f, v in (("--radius", args.radius), ("--angle-pitch", args.angle_pitch),
                            ("--sweep-radius", getattr(args, "sweep_radius", None)),
                            ("--angle-step", getattr(args, "angle_step", None))) if v is not None]
    if given:
        raise InputError(f"{' and '.join(given)} describe{'s' if len(given) == 1 else ''} a convex, sector or swept "
                         "probe, and the geometry is linear: pass --geometry convex, sector or swept with "
                         f"{'it' if len(given) == 1 else 'them'} (or leave {'it' if len(given) == 1 else 'them'} "
                         "out)")


#: Tightest curvature of a convex array, mm (microconvex and endocavity arrays: 8-25 mm, abdominal 40-80 mm).
MIN_CONVEX_RADIUS_MM = 8.0


def _check_radius_units(args) -> None:
    """A ``--radius`` no convex array has: below 1 mm it reads as metres and is refused (the fan's geometry would be
    a sector's, every lateral position wrong); below :data:`MIN_CONVEX_RADIUS_MM` it reads as centimetres, a note
    on stderr (registered as given)."""
    from femreg.errors import InputError

    r = float(args.radius)
    if r < 1.0:
        raise InputError(f"--radius {r:g} mm: no convex array is that tight (microconvex 8-25 mm, abdominal 40-80 "
                         f"mm); in metres it would be --radius {1e3 * r:g} (mm); a phased array, apex on the face: "
                         "--geometry sector")
    if r < MIN_CONVEX_RADIUS_MM:
        who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
        print(f"{who}: note: --radius {r:g} mm is tighter than convex arrays are (microconvex 8-25 mm, abdominal "
              f"40-80 mm): in centimetres it would be --radius {10 * r:g}; registered as given", file=sys.stderr)


def _geometry(args):
    import femreg
    from femreg.errors import InputError

    if args.angle_pitch is None:
        raise InputError(f"--geometry {args.geometry} needs --angle-pitch (degrees between rays)")
    if args.geometry == "convex":
        if args.radius is None:
            raise InputError("--geometry convex needs --radius (mm from the apex to the face)")
        geo = femreg.Convex(radius_mm=args.radius, angle_pitch_deg=args.angle_pitch)
        _check_radius_units(args)
        return geo
    if args.radius not in (None, 0.0):
        raise InputError("--geometry sector has its apex on the face: no --radius")
    return femreg.Sector(angle_pitch_deg=args.angle_pitch)


def _refuse_curved(fr, path, advice: str = "") -> None:
    """Frames whose header states a convex or phased array are not registered as a linear array's (their rays
    would be taken for parallel lines) unless ``--geometry`` is given (``advice``: what to do instead, for a
    command without ``--geometry``)."""
    from femreg.errors import InputError
    from femreg.io.checks import geometry_hint, header_axes, header_fields

    hint = geometry_hint(header_fields(fr.metadata), header_axes(fr.metadata), fr.shape[1])
    if hint:
        raise InputError(f"{path}: {hint}; " + (advice or "pass those flags (or --geometry linear if the frames "
                                                           "are on a Cartesian grid already)"))


def _check_stated_geometry(fr, path, beam, args) -> None:
    """A ``--geometry convex|sector`` whose radius or angle pitch differs by more than 2 % from what the file's own
    header states (:func:`femreg.io.checks.geometry_fields`: a radius field, an angle-pitch field or a vector of
    the rays' angles) is refused: an angle pitch off by a factor scales every lateral displacement and strain and
    passes the speckle check.  ``--no-orientation-check`` registers it as given."""
    from femreg.errors import InputError
    from femreg.io.checks import geometry_fields, geometry_hint, header_axes, header_fields

    if getattr(args, "no_orientation_check", False):
        return
    fields, axes = header_fields(fr.metadata), header_axes(fr.metadata)
    g = geometry_fields(fields, axes, fr.shape[1])
    if not g:
        return
    given_r = float(getattr(beam, "radius_mm", 0.0) or 0.0)
    wrong = []
    if "angle_pitch_deg" in g and abs(float(beam.angle_pitch_deg) / g["angle_pitch_deg"] - 1.0) > 0.02:
        wrong.append(f"--angle-pitch {float(beam.angle_pitch_deg):g} deg against {g['angle_pitch_deg']:.4g} deg")
    if "radius_mm" in g and abs(given_r - g["radius_mm"]) > 0.02 * g["radius_mm"]:
        wrong.append(f"--radius {given_r:g} mm against {g['radius_mm']:.4g} mm" if given_r else
                     f"--geometry sector (apex on the face) against a convex radius of {g['radius_mm']:.4g} mm")
    if wrong:
        raise InputError(f"{path}: the probe given contradicts the file's own header ({'; '.join(wrong)}); "
                         f"{geometry_hint(fields, axes, fr.shape[1])}, or --no-orientation-check to register "
                         "with the values given")


def beam_start_range(fr, path, args) -> float:
    """The first sample's range (mm) of convex / sector frames: ``--origin`` or the file's origin when given,
    else the start depth the header states (:func:`femreg.io.checks.unapplied_start_depth`: ``t0``,
    ``start_depth``, ...), applied with a note on stderr, since every ray's physical position depends on it (a
    convex pair read from 0: 10.27 % total strain error, 6.74 % from the header's 3 mm: CHANGELOG); else 0."""
    from femreg.io.checks import unapplied_start_depth

    depth, why = unapplied_start_depth(fr.metadata, fr.origin, getattr(args, "sound_speed", None))
    if depth is None:
        return float(fr.origin[0])
    who = " ".join(["femreg", getattr(args, "command", None) or ""]).strip()
    print(f"{who}: note: {path}: the first sample taken at range {depth:.4g} mm, the start depth the header "
          f"states ({why}): the rays' geometry depends on it; --origin R0 0 overrides it", file=sys.stderr)
    return float(depth)


def run(args) -> int:
    import femreg
    from femreg.errors import InputError

    kw = registration_kwargs(args)
    refuse_unused_geometry(args)
    from ._volume import read_volume_file, register_volumes
    vol = read_volume_file(args.reference, volume=args.volume, origin=getattr(args, "origin", None),
                           spacing=getattr(args, "spacing", None), variable=getattr(args, "variable", None),
                           check_sampling=not getattr(args, "no_orientation_check", False))
    if vol is not None:                 # RF volumes (spacing with 3 values)
        if getattr(args, "transpose", False):
            raise InputError("--transpose is for frames (lines x samples); transpose a volume's axes before "
                             "saving it (axial, lateral, elevational)")
        if args.geometry in ("convex", "sector"):
            raise InputError(f"--geometry {args.geometry} is for frames; a swept probe's volumes take --geometry "
                             "swept")
        if args.geometry == "swept":
            kw["geometry"] = _swept(args)
        return register_volumes(args, vol, kw)
    if args.geometry == "swept":
        raise InputError(f"--geometry swept needs a volume file (.npz with spacing of 3 values), got "
                         f"{args.reference}")
    if args.refine is not None:
        from femreg.refine import REFINE_NAMES, refine_name

        r = refine_name(args.refine)            # the names femreg.register takes ("slip": SLIP_REFINEMENT)
        if r.isdigit():
            kw["refine"] = int(r)
        elif r in REFINE_NAMES:
            kw["refine"] = None if r in ("none", "off") else r
        else:
            raise InputError(f"--refine takes a number of passes, auto, slip or none, got {args.refine!r}")
    beam = _geometry(args) if args.geometry in ("convex", "sector") else None
    if beam is not None:                # the range step alone: the rays are --angle-pitch apart
        args.spacing = beam_spacing_args(args, beam)
    try:
        ref_fr = frames_from_args(args, args.reference)
    except InputError as exc:
        raise (beam_spacing_error(exc, beam) if beam is not None else exc) from None
    if args.geometry == "linear" and not getattr(args, "geometry_given", False):
        _refuse_curved(ref_fr, args.reference)
    if beam is not None:
        _check_stated_geometry(ref_fr, args.reference, beam, args)
        r0 = beam_start_range(ref_fr, args.reference, args)
    if args.moving is None:
        i, j = args.pair or (0, 1)
        mov_fr = ref_fr
        if ref_fr.n_frames < 2:
            if args.pair is not None:
                raise InputError(f"{args.reference} holds one frame, so --pair {i} {j} has no second frame to pick: "
                                 f"give the moving frame's file too (femreg register REF MOV)")
            raise InputError(f"{args.reference} holds one frame: give the moving frame's file too "
                             f"(femreg register REF MOV), or a file of several frames (--pair I J picks two)")
        if args.pair is None and ref_fr.n_frames > 2:
            # a cine loop: frames 0 -> 1 are rarely the pair meant; say so (femreg track / elastogram take all)
            print(f"femreg register: note: {args.reference} holds {ref_fr.n_frames} frames: registering frames "
                  "0 -> 1 (--pair I J picks others; femreg track follows every frame, femreg elastogram picks "
                  "the pairs of a freehand loop)", file=sys.stderr)
    else:
        i, j = args.pair or (0, 0)
        mov_fr = frames_from_args(args, args.moving)
        if not np.allclose(ref_fr.spacing, mov_fr.spacing):
            raise InputError(f"spacing differs between frames: {tuple(ref_fr.spacing)} vs {tuple(mov_fr.spacing)}")
        if args.pair is None and max(ref_fr.n_frames, mov_fr.n_frames) > 1:
            # two multi-frame files: say which frames are registered; a 3D file may be meant as one volume
            print(f"femreg register: note: {args.reference} holds {ref_fr.n_frames} and {args.moving} "
                  f"{mov_fr.n_frames} frames: registering frame 0 of each (--pair I J picks others; --volume "
                  "reads each file as one RF volume)", file=sys.stderr)
    ref = _frame(ref_fr, i, args.reference)
    mov = _frame(mov_fr, j, args.moving or args.reference)
    if args.moving is not None and np.shape(ref) != np.shape(mov):
        dims = " x ".join
        raise InputError(f"{args.reference} and {args.moving} hold frames of different shapes, "
                         f"{dims(map(str, np.shape(ref)))} and {dims(map(str, np.shape(mov)))} (axial x lateral"
                         f"{' x elevational' if np.ndim(ref) == 3 else ''}): both frames of a pair come from one "
                         "recording (check the files and --shape)")
    if np.array_equal(ref, mov):
        # nothing moved: the solve would run to its iteration limit on ||du|| / ||u|| with u = 0 and exit 0
        which = (f"--pair {i} {j} names frame {i} twice" if args.moving is None else
                 f"{args.reference} frame {i} and {args.moving} frame {j} hold the same samples")
        pick = "--pair I J, counted from 0" if args.moving is None else "the moving frame's file, or --pair I J"
        raise InputError(f"{which}: identical frames, nothing to register (pick two different frames: {pick})")
    if args.moving is not None and "iq" in ref_fr.metadata and not args.no_orientation_check:
        # two IQ files: their sign convention is checked on the pair (one file of several frames is checked as read)
        from ..orientation import check_iq_sign

        check_iq_sign(ref, mov, ref_fr.spacing, ref_fr.metadata["iq"], where=f"{args.reference}, {args.moving}: ",
                      metadata=ref_fr.metadata)
    if not str(args.output).endswith(".npz"):
        raise InputError(f"-o must name a .npz file, got {args.output}")

    files = (ref_fr.metadata or {}).get("files")
    if args.moving is None and args.pair is not None and files and len(files) == ref_fr.n_frames:
        # a folder of numbered files: name them, frame1.raw is frame 0 (a 1-based --pair registers other frames)
        print(f"femreg register: note: registering {files[i]} -> {files[j]} (frames {i} -> {j} of "
              f"{args.reference}, counted from 0)", file=sys.stderr)
    spacing, origin = ref_fr.spacing, ref_fr.origin
    if beam is not None:                # range step and first range from the file; rays centred on angle 0
        kw["geometry"] = beam
        spacing, origin = float(spacing[0]), (r0, 0.0)
    from ..autoalpha import showing_progress

    try:
        with showing_progress(not args.no_progress):
            res = femreg.register(ref, mov, spacing=spacing, origin=origin, **kw)
    except InputError:
        raise                      # bad input: exit 2 from the dispatcher
    except Exception as exc:  # noqa: BLE001 - a computation that fails is a failed pair (1), not bad input (2)
        msg = " ".join(str(exc).split()) or type(exc).__name__
        print(f"femreg register: failed: the registration stopped ({type(exc).__name__}: {msg})", file=sys.stderr)
        return 1
    # the frames of one file registered, so that `femreg plot --reference FILE` draws the reference frame's B-mode
    one_file = args.moving is None and not getattr(args, "frames", None)
    res.save(args.output, **({"pair": np.asarray([i, j], np.int64)} if one_file else {}))
    # a line to read (the result's repr is the library's); a failure's message follows once, as the error line
    print(f"pair: ncc {res.ncc_before:.3f} -> {res.ncc_after:.3f}, nit {res.nit}, {res.mesh.p.shape[1]} nodes, "
          f"regularizer {res.regularizer}, alpha {res.alpha:g}" + (f"; {res.message}" if res.success else ""))
    if res.excluded:
        print(f"femreg register: left out of the mesh (the rest is registered): {res.excluded}")
    note = getattr(getattr(res, "refinement", None), "note", None)
    if note and "decorrel" in note:        # decorrelated speckle (refined anyway, or not split for it)
        print(f"femreg register: note: {note.replace('refine=None', '--refine none')}")
    for part in (res.message or "").split("; "):       # femreg.orientation.frequency_note: the spacing suspect
        if part.startswith("the RF carrier reads "):
            print(f"femreg register: note: {part}")
    print(f"wrote {args.output}")
    if not res.success:
        reason = res.message.removeprefix("FAILED: ")
        print(f"femreg register: failed: the registration failed its checks: {reason}", file=sys.stderr)
        return 1
    if not (np.isfinite(res.ncc_after) and res.ncc_after >= args.min_ncc):
        print(f"femreg register: FLAGGED: low-quality pair (NCC after {res.ncc_after:.3f} < --min-ncc "
              f"{args.min_ncc})", file=sys.stderr)
        return 1
    return 0
