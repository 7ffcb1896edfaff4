"""``femreg invert PAIR.npz -o MU.npz``: relative shear-modulus image from a registration result.

PAIR.npz is a file written by ``femreg register`` (or :meth:`femreg.RegistrationResult.save`, or a volume's
:meth:`femreg.volume_result.VolumeResult.save`); the inversion (:func:`femreg.invert`) runs on its mesh (a
refined registration: on the tensor mesh of its unrefined element size), or on a structured mesh of
``--element-size``.  MU.npz is reloadable with :func:`femreg.inversion.load_inversion`;
``femreg plot MU.npz`` draws the modulus image beside the axial strain (a volume: three orthogonal slices of the
modulus, its uncertainty and the axial strain through ``--slice``).  ``--model auto`` (default) picks plane
strain, plane stress or an effective model from the data (a volume: the 3D model); ``--reference X0 X1 Y0 Y1
KPA`` (a volume: ``X0 X1 Y0 Y1 Z0 Z1 KPA``) adds moduli in kPa, and ``--region`` takes four numbers (a volume:
six).  Exit 0 on success; 2 on bad input (one-line reason), among it a registration that failed its own
check (``success`` False: its displacement is not trustworthy) unless ``--allow-failed``; 1 when the
optimisation fails or the result is flagged (beta at its grid's edge, modulus at its bound, model against
the data, modulus against strain), or when it ran on a failed registration with ``--allow-failed`` (the result is still
written, with ``success = False`` and the reason).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def add_parser(subparsers):
    p = subparsers.add_parser(
        "invert", help="shear-modulus image from a registration result (FE inversion)",
        description="Relative shear modulus (median 1) per element from the displacement in PAIR.npz: "
                    "plane-stress (lambda_bar = 2), plane-strain or effective model (auto: from the data) with the measured displacement on the "
                    "boundary, total-variation regularisation of log mu, adjoint gradient, L-BFGS-B.  A volume's "
                    "result (femreg register on RF volumes) is inverted on hexahedra with the 3D model; its "
                    "--region and --reference boxes take a z interval too.")
    p.add_argument("result", help="registration result .npz (femreg register -o ...)")
    p.add_argument("-o", "--output", required=True, help="output .npz (missing folders are created)")
    p.add_argument("--model", default="auto", choices=("auto", "plane-stress", "plane-strain", "3d"),
                   help="forward model (default auto: from the data's lateral/axial strain ratio; 3d for a "
                        "volume's result)")
    p.add_argument("--beta", type=float, help="regularisation weight (default: chosen by the L-curve rule)")
    p.add_argument("--element-size", metavar="MM", type=float, nargs="+",
                   help="invert on a structured mesh of this element size (one value, or axial and lateral; a "
                        "volume: one value or axial, lateral and elevational; default: the registration mesh, or for a "
                        "refined registration its unrefined element size)")
    p.add_argument("--region", metavar="MM", type=float, nargs="+",
                   help="invert over this box only: X0 X1 Y0 Y1 (a volume: X0 X1 Y0 Y1 Z0 Z1), mm")
    p.add_argument("--regularization", default="tv", choices=("tv", "tikhonov"), help="default tv")
    p.add_argument("--poisson", type=float, help="plane strain: Poisson ratio (default 0.495)")
    p.add_argument("--maxiter", type=int, default=400, help="L-BFGS-B iterations per solve (default 400)")
    p.add_argument("--reference", metavar="V", type=float, nargs="+",
                   help="X0 X1 Y0 Y1 KPA (a volume: X0 X1 Y0 Y1 Z0 Z1 KPA): a box (mm) of known Young's modulus "
                        "(kPa); also write shear and Young's moduli in kPa")
    p.add_argument("--images", metavar="FILE", nargs="+",
                   help="the registered frames (reference and moving file, or one multi-frame file with --pair; a "
                        "volume's result: its .npz volume file(s)): also run the one-step inversion from the images")
    p.add_argument("--pair", metavar=("I", "J"), type=int, nargs=2,
                   help="with --images: frame indices of reference and moving (default: the frames the result "
                        "was registered from (femreg register FILE --pair, femreg batch, femreg track's frame "
                        "K: 0 K), else 0 1 in one file, 0 0 in two)")
    p.add_argument("--no-uncertainty", action="store_true", help="skip the uncertainty map (Laplace approximation)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (optimiser iterations)")
    p.add_argument("--vtu", metavar="OUT.vtu", help="also write a ParaView file")
    p.add_argument("--png", metavar="OUT.png", help="also draw the modulus image beside the axial strain")
    add_slice_arg(p)
    p.add_argument("--no-orientation-check", action="store_true",
                   help="with --images: read them without the checks that refuse frames that look transposed, a "
                        "swapped spacing or IQ phases against --iq-frequency (femreg.orientation)")
    p.add_argument("--allow-failed", action="store_true",
                   help="invert a registration that failed its own check anyway (the result is flagged, exit 1)")
    from ._common import add_reader_args

    add_reader_args(p)
    p.set_defaults(func=run)
    return p


#: Young's moduli (kPa) of soft tissue and elastography phantoms, about; a --reference outside is likely given in
#: Pa or MPa
KPA_RANGE = (0.1, 2000.0)


def _images(args, spacing=None, shape=None):
    """(reference, moving) frames of --images, read like ``femreg register`` reads them; ``spacing``: the
    registration's (mm), which a file without its own takes (:func:`frames_on_result_grid`).  One file: frames
    ``--pair``, by default those the result was registered from (0 1 when it does not say)."""
    from femreg.errors import InputError

    from ._common import frames_on_result_grid, registered_frames
    from .register_cmd import _frame

    if len(args.images) > 2:
        raise InputError(f"--images takes one or two files, got {len(args.images)}")
    ref_fr = frames_on_result_grid(args, args.images[0], spacing, shape)
    if len(args.images) == 1:
        found = None if getattr(args, "frames", None) else registered_frames(args.result)
        i, j = args.pair or (found[:2] if found else (0, 1))
        mov_fr = ref_fr
    else:
        i, j = args.pair or (0, 0)
        mov_fr = frames_on_result_grid(args, args.images[1], spacing, shape)
    return _frame(ref_fr, i, args.images[0]), _frame(mov_fr, j, args.images[-1])


def _volumes(args):
    """(reference, moving) volumes of --images for a volume's result: one ``.npz`` of a volume sequence (frames
    ``--pair I J``, default 0 1) or two ``.npz`` volume files (``--pair``, default 0 0 of each), read as
    ``femreg register`` reads volumes (an ``rf`` array, ``spacing`` of 3 values)."""
    from femreg.errors import InputError

    from ._common import frame_index
    from ._volume import read_volume_file

    if len(args.images) > 2:
        raise InputError(f"--images takes one or two files, got {len(args.images)}")
    arrays = []
    for path in args.images:
        got = read_volume_file(path)
        if got is None:
            raise InputError(f"{path}: not a volume file (an .npz with an rf array (n_x, n_y, n_z) or (n_frames, "
                             "n_x, n_y, n_z) and spacing of 3 values); a volume's result needs its volumes")
        arrays.append(np.asarray(got[0]))
    i, j = args.pair or ((0, 1) if len(arrays) == 1 else (0, 0))
    out = []
    for arr, k, path in ((arrays[0], i, args.images[0]), (arrays[-1], j, args.images[-1])):
        if arr.ndim == 3:
            if k != 0:
                raise InputError(f"{path} holds one volume; --pair index {k} does not exist (counted from 0: 0)")
            out.append(arr)
        else:
            out.append(arr[frame_index(k, arr.shape[0], path, "--pair")])
    if len(arrays) == 1 and arrays[0].ndim == 3:
        raise InputError(f"{args.images[0]} holds one volume; the one-step inversion needs the reference and the "
                         "moving volume (a sequence file, or two files)")
    return out[0], out[1]


def _boxes(args, volume):
    """(region, reference) for :func:`femreg.invert` from --region / --reference, their counts checked against
    the result's dimension."""
    from femreg.errors import InputError

    n = 6 if volume else 4
    names = "X0 X1 Y0 Y1 Z0 Z1" if volume else "X0 X1 Y0 Y1"
    kind = "a volume's result" if volume else "a 2D result"

    def box(v):
        return tuple(float(a) for a in v) if volume else ((v[0], v[1]), (v[2], v[3]))

    region = reference = None
    if args.region is not None:
        if len(args.region) != n:
            raise InputError(f"--region takes {n} numbers ({names}, mm) for {kind}, got {len(args.region)}: "
                             f"{' '.join(f'{v:g}' for v in args.region)}")
        region = box(args.region)
    if args.reference is not None:
        if len(args.reference) != n + 1:
            raise InputError(f"--reference takes {n + 1} numbers ({names} mm, then KPA) for {kind}, got "
                             f"{len(args.reference)}: {' '.join(f'{v:g}' for v in args.reference)}")
        reference = (box(args.reference[:n]), float(args.reference[n]))
        kpa = reference[1]
        lo, hi = KPA_RANGE
        if not lo <= kpa <= hi:     # the moduli in kPa all scale with it: say so before they are written
            other = ("Pa", kpa / 1e3) if kpa > hi else ("MPa", kpa * 1e3)
            print(f"femreg invert: note: --reference {kpa:g} kPa lies outside the Young's moduli of soft tissue and "
                  f"phantoms ({lo:g}-{hi:g} kPa), and every modulus in kPa scales with it; if it is in {other[0]}, "
                  f"pass {other[1]:g}", file=sys.stderr)
    return region, reference


def add_slice_arg(p):
    """``--slice``: where the three slices of a volume's modulus picture cut."""
    p.add_argument("--slice", nargs="+", metavar="WHERE",
                   help="a volume's picture: the point X Y Z (mm) its three orthogonal slices pass through, or "
                        "centre (default), stiffest, softest (the core of the stiffest / softest region)")


def slice_position(args):
    """None, a word of :data:`femreg.volplot.SLICE_CHOICES` or an (x, y, z) point from ``--slice``."""
    from femreg.errors import InputError
    from femreg.volplot import SLICE_CHOICES

    v = getattr(args, "slice", None)
    if v is None:
        return None
    if len(v) == 1 and v[0] in SLICE_CHOICES:
        return v[0]
    try:
        point = tuple(float(a) for a in v)
    except ValueError:
        point = ()
    if len(point) != 3 or not all(np.isfinite(point)):
        raise InputError(f"--slice takes X Y Z (mm) or one of {', '.join(SLICE_CHOICES)}, got {' '.join(v)}")
    return point


def run(args) -> int:
    import femreg
    from femreg.errors import InputError

    out = Path(args.output)
    if out.suffix.lower() != ".npz":
        raise InputError(f"-o must name a .npz file, got {out}")
    for flag, path, ext in (("--vtu", args.vtu, ".vtu"), ("--png", args.png, ".png")):
        if path and Path(path).suffix.lower() != ext:
            raise InputError(f"{flag} must name a {ext} file, got {path}")
    if args.no_orientation_check and not args.images:    # it would be ignored
        raise InputError("--no-orientation-check applies to the frames of --images FILE(S), and none were given")
    if args.pair is not None and not args.images:        # it would be ignored
        raise InputError(f"--pair {' '.join(str(k) for k in args.pair)} picks the frames of --images FILE(S), and "
                         "none were given")
    reg = femreg.load_result(args.result)
    volume = np.shape(reg.mesh.p)[0] == 3
    kind = "a volume's result" if volume else "a 2D result"
    es = args.element_size
    if es is not None and len(es) not in ((1, 3) if volume else (1, 2)):
        counts = "1 or 3 values (mm: axial, lateral, elevational)" if volume else "1 or 2 values (mm)"
        raise InputError(f"--element-size takes {counts} for {kind}, got {len(es)}: "
                         f"{' '.join(f'{v:g}' for v in es)}")
    region, reference = _boxes(args, volume)
    if volume and args.model in ("plane-stress", "plane-strain"):
        raise InputError(f"--model {args.model} is a 2D model; {args.result} is a volume's result: use --model 3d "
                         "(or auto)")
    if not volume and args.model == "3d":
        raise InputError(f"--model 3d needs a volume's result; {args.result} is 2D")
    slice_at = slice_position(args)
    if slice_at is not None and not volume:
        raise InputError("--slice applies to a volume's inversion only; this result is 2D")
    failed_reg = not reg.success and bool(reg.message)     # a result made by hand has no verdict (no message)
    if failed_reg and not args.allow_failed:
        raise InputError(f"{args.result} is a failed registration ({reg.message.removeprefix('FAILED: ')}); its "
                         "displacement is not trustworthy: register the pair again, or pass --allow-failed")
    ref_img, mov_img = ((_volumes(args) if volume else _images(args, getattr(reg, "spacing", None), getattr(reg, "shape", None)))
                        if args.images else (None, None))
    res = femreg.invert(reg, model=args.model, beta=args.beta, region=region,
                        element_size=None if es is None else (es[0] if len(es) == 1 else tuple(es)),
                        regularization=args.regularization, poisson=args.poisson, maxiter=args.maxiter,
                        reference=reference, uncertainty=not args.no_uncertainty, reference_image=ref_img,
                        moving_image=mov_img, progress=not args.no_progress)
    if failed_reg:
        res.success = False
        res.message = f"inverted from a failed registration ({args.result}); " + res.message
    res.save(out)
    # a failed or flagged result's message is printed once, on stderr below
    # a line to read (the library's repr names Python fields: success=False, n_el=...)
    q5, q95 = np.percentile(res.mu, [5, 95])
    said = res.message if (res.success or failed_reg) and res.message else ""
    print(f"inversion: {'done' if res.success else 'flagged'}, model {res.model}, beta {res.beta:.3g}, "
          f"{res.mesh.t.shape[1]} elements, mu 5-95 % {q5:.3g}-{q95:.3g} (median 1), {res.nit} iterations"
          + (f"; {said}" if said else ""))
    where = "over the region" if region is not None else "over the mesh"
    print(f"modulus contrast {where}: {q95 / q5:.3g} (95th / 5th percentile of mu: {q95:.3g} / {q5:.3g}; "
          f"median 1)")
    print(f"model: {res.model} ({res.model_rule})")
    if res.one_step is not None:
        o = res.one_step
        print(f"one-step inversion from the images: image term {o['psi_two_step']:.4g} -> {o['psi_one_step']:.4g} "
              f"({o['nit']} Gauss-Newton iterations, {o['seconds']:.1f} s)")
    if res.uncertainty is not None:
        print(f"uncertainty: median std of log mu {np.nanmedian(res.uncertainty):.3g} over "
              f"{int(res.constrained.sum())}/{res.constrained.size} constrained elements")
    for note in res.notes:
        print(f"note: {note}")
    if res.youngs_modulus_kpa is not None:
        q5, q50, q95 = np.percentile(res.youngs_modulus_kpa, [5, 50, 95])
        print(f"Young's modulus E = 3 mu: median {q50:.4g} kPa (5-95 %: {q5:.4g}-{q95:.4g} kPa)")
    print(f"wrote {out}")
    if args.vtu:
        res.to_vtu(args.vtu)
        print(f"wrote {args.vtu}")
    if args.png:
        import matplotlib.pyplot as plt

        plt.close(res.plot(args.png, **({} if slice_at is None else {"at": slice_at})))
        print(f"wrote {args.png}")
    if failed_reg:
        print(f"femreg invert: FLAGGED: inverted from a failed registration ({args.result})", file=sys.stderr)
        return 1
    if not res.success:
        what = "" if res.flags else "failed: the optimisation failed: "
        print(f"femreg invert: {what}{res.message}", file=sys.stderr)
        return 1
    return 0


def is_inversion_file(path) -> bool:
    from femreg.inversion import is_inversion_file as _is

    return _is(path)


def plot_inversion_file(args) -> int:
    """``femreg plot MU.npz`` for a file of ``femreg invert``: the modulus image beside the axial strain
    (-o PNG; a volume's: three orthogonal slices through --slice) and, with --vtu, a ParaView file."""
    import matplotlib.pyplot as plt

    from femreg.errors import InputError
    from femreg.inversion import load_inversion

    out = Path(args.output) if args.output else Path(args.result).with_suffix(".png")
    if out.suffix.lower() != ".png":
        raise InputError(f"-o must name a .png file, got {out}")
    res = load_inversion(args.result)
    at = slice_position(args)
    if at is not None and res.dim != 3:
        raise InputError(f"--slice applies to a volume's inversion only; {args.result} is 2D")
    plt.close(res.plot(out, dpi=args.dpi, **({} if at is None else {"at": at})))
    print(f"wrote {out}")
    if getattr(args, "vtu", None):
        res.to_vtu(args.vtu)
        print(f"wrote {args.vtu}")
    from ._common import failed_notice

    return failed_notice(args.result, res.success, res.message)
