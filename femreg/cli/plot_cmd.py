"""``femreg plot RESULT.npz``: summary PNG of a registration result and optional VTU/XDMF exports."""
from __future__ import annotations

import sys
from pathlib import Path

from ..errors import InputError
from ._common import (add_reader_args, failed_notice, frame_index, frames_from_args,  # noqa: F401
                      frames_on_result_grid, registered_frames)  # failed_notice: also here


def add_parser(subparsers):
    p = subparsers.add_parser(
        "plot", help="figures (PNG) and ParaView files (VTU/XDMF) of a registration result",
        description="Plot a result .npz written by `femreg register`: B-mode (with --reference) or mesh, "
                    "ux, uy (mm), exx, eyy, exy (%) with colour bars and mm axes (a red banner when the result "
                    "failed; the image outside the mesh hatched), and the per-element quality map "
                    "(OUT_quality.png) when the result holds one.  A file of `femreg invert` gets the modulus "
                    "image, its uncertainty and the axial strain (a volume's: three orthogonal slices of each "
                    "through --slice).  Optionally export the mesh with nodal "
                    "displacement and strains to VTU/XDMF and render the mesh with pyvista.")
    p.add_argument("result", help="result .npz (keys mesh_points, mesh_cells, u, ux, uy, exx, eyy, exy, ...)")
    p.add_argument("-o", "--output", metavar="OUT.png",
                   help="figure path (default: RESULT with .png; missing folders are created)")
    p.add_argument("--vtu", metavar="OUT.vtu", help="also write the mesh, displacement and strains as VTU")
    p.add_argument("--xdmf", metavar="OUT.xdmf", help="also write them as XDMF (+ .h5)")
    p.add_argument("--render", metavar="OUT.png", help="also render the mesh coloured by --field with pyvista")
    p.add_argument("--field", default="exx", choices=("ux", "uy", "exx", "eyy", "exy"),
                   help="field for --render (default exx, element-centre values; strains in %%, displacement in mm)")
    p.add_argument("--reference", metavar="FILE",
                   help="reference RF (any readable format) for the B-mode panel, drawn on the result's grid (a "
                        "file that stores no spacing needs no --spacing: the result's is used)")
    p.add_argument("--frame", type=int, default=None,
                   help="frame of --reference to use, counted from 0 (default: the frame the result is "
                        "registered on: I of femreg register FILE --pair I J or femreg batch, the first of a "
                        "femreg track --frames selection; else 0)")
    p.add_argument("--overlay", action="store_true", help="draw the fields over the B-mode (needs --reference)")
    p.add_argument("--shear", action="store_true",
                   help="also draw the shear-strain product OUT_shear.png: e_xy per element, its predicted "
                        "precision relative to the image's median (from the element's NCC and size and the "
                        "speckle cell of --reference, which it needs) and the element's width in lateral speckle "
                        "cells (below 1 outlined)")
    p.add_argument("--dpi", type=int, default=100, help="figure resolution (default 100)")
    p.add_argument("--no-orientation-check", action="store_true",
                   help="with --reference: read it without the checks that refuse frames that look transposed, a "
                        "swapped spacing or IQ phases against --iq-frequency (femreg.orientation)")
    from .invert_cmd import add_slice_arg

    add_slice_arg(p)
    add_reader_args(p, group_title="--reference file options")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    try:
        return _run(args)
    except OSError as exc:  # unwritable output folder, full disk: a one-line reason, not a traceback
        name = getattr(exc, "filename", None) or ""
        raise InputError(f"cannot write {name}: {exc.strerror or exc}".replace("write :", "write:")) from None


def _run(args) -> int:
    import numpy as np

    from ..io import export_result
    from ..io.results import as_result_dict
    from ..io.results import element_strains
    from ..plot import plot_result, render_mesh

    for flag, path, ext in (("--vtu", args.vtu, ".vtu"), ("--xdmf", args.xdmf, ".xdmf"),
                            ("--render", args.render, ".png")):
        if path and Path(path).suffix.lower() != ext:
            raise InputError(f"{flag} must name a {ext} file, got {path}")
    if args.no_orientation_check and not args.reference:     # it would be ignored
        raise InputError("--no-orientation-check applies to the frames of --reference FILE, and none was given")
    if args.frame is not None and not args.reference:     # it would be ignored: the picture is not what was asked
        raise InputError(f"--frame {args.frame} picks a frame of --reference FILE, and none was given (a track's "
                         "frame K is its file OUT/frame_KKK.npz)")
    # ---- a shear-modulus file of `femreg invert` has its own figure
    from .invert_cmd import is_inversion_file, plot_inversion_file
    if is_inversion_file(args.result):
        return plot_inversion_file(args)
    # ----
    from ..volume_result import is_volume_result

    if is_volume_result(args.result):
        return plot_volume_result(args)
    if getattr(args, "slice", None) is not None:
        raise InputError("--slice applies to the picture of a volume's result or inversion; this result is 2D")
    res = as_result_dict(args.result)
    if args.dpi <= 0:
        raise InputError(f"--dpi must be positive, got {args.dpi}")
    reference, bmode_title = None, "B-mode"
    if args.reference:
        fr = frames_on_result_grid(args, args.reference, res.get("spacing"), res.get("shape"))
        found = None if getattr(args, "frames", None) else registered_frames(args.result, res)
        own, what = (found[0], found[2]) if found else (None, "")
        k = args.frame if args.frame is not None else (own if own is not None and own < fr.n_frames else 0)
        reference = fr.frames[frame_index(k, fr.n_frames, args.reference, "--frame")]
        if own is not None and k != own:
            print(f"femreg plot: note: {args.result} {what}: the B-mode of --frame {k} is not its reference "
                  f"frame ({own}, the default)", file=sys.stderr)
        if fr.n_frames > 1:
            bmode_title = f"B-mode, frame {k}"
    elif args.overlay or args.shear:
        flag = "--overlay" if args.overlay else "--shear"
        why = "" if args.overlay else " (its speckle cell sets the precision of e_xy)"
        raise InputError(f"{flag} needs --reference FILE{why}")
    out = Path(args.output) if args.output else Path(args.result).with_suffix(".png")
    if out.suffix.lower() != ".png":
        raise InputError(f"-o must name a .png file, got {out}")
    import matplotlib.pyplot as plt

    fig = plot_result(res, out, reference=reference, overlay=args.overlay, dpi=args.dpi, bmode_title=bmode_title)
    plt.close(fig)
    print(f"wrote {out}")
    if "success" in res and not bool(res["success"]):
        print(f"femreg plot: note: {args.result} is a failed registration ({res.get('message', '')}); the figure "
              "says so in its title", file=sys.stderr)
    if res.get("quality") is not None and np.size(res["quality"]) == np.shape(res["mesh_cells"])[1]:
        from ..plot import plot_quality, quality_pair

        qout = out.with_name(out.stem + "_quality.png")
        plt.close(plot_quality(res["mesh_points"], res["mesh_cells"], res["quality"], qout, dpi=args.dpi,
                               pair=quality_pair(res)))
        print(f"wrote {qout}")
    if args.shear:
        _shear_figure(res, reference, out, args.dpi)
    for path in (args.vtu, args.xdmf):
        if path:
            export_result(res, path)
            print(f"wrote {path}")
    if args.render:
        p, t = res["mesh_points"], res["mesh_cells"]
        if args.field in ("ux", "uy"):
            u = np.asarray(res["u"], dtype=float)
            vals, name = (u[0::2] if args.field == "ux" else u[1::2]), f"{args.field} (mm)"
        else:
            vals = 100.0 * element_strains(p, t, res["u"])[:, ("exx", "eyy", "exy").index(args.field)]
            name = f"{args.field} (%)"
        render_mesh(p, t, vals, args.render, name=name)
        print(f"wrote {args.render}")
    return failed_notice(args.result, res.get("success", True), res.get("message", ""), res.get("flag", ""))


def _shear_figure(res, reference, out, dpi):
    """OUT_shear.png: :func:`femreg.shear.shear_strain_map` of the result on ``reference`` (the registered frame,
    on the result's grid), drawn by :func:`femreg.plot.plot_shear`."""
    from types import SimpleNamespace

    import matplotlib.pyplot as plt
    import numpy as np

    from ..plot import plot_shear
    from ..shear import narrow_elements, shear_strain_map

    q = res.get("quality")
    n_el = np.shape(res["mesh_cells"])[1]
    if q is None or np.size(q) != n_el:
        raise InputError("--shear needs the result's per-element quality (element NCC), which this file does not "
                         "hold: register the pair again with femreg register")
    mesh = SimpleNamespace(p=np.asarray(res["mesh_points"], float), t=np.asarray(res["mesh_cells"], np.int64))
    result = SimpleNamespace(mesh=mesh, u=np.asarray(res["u"], float), quality=np.asarray(q, float),
                             spacing=tuple(np.asarray(res["spacing"], float).ravel()))
    sm = shear_strain_map(result, reference)
    sout = out.with_name(out.stem + "_shear.png")
    narrow = int(np.sum(narrow_elements(sm)))
    cell = sm["cell"]
    plt.close(plot_shear(mesh.p, mesh.t, sm, sout, dpi=dpi,
                         title=f"speckle cell {cell[0]:.2f} x {cell[1]:.2f} mm (axial x lateral)"))
    print(f"wrote {sout} (e_xy per element, its relative predicted precision; speckle cell {cell[0]:.2f} x {cell[1]:.2f} "
          f"mm; {narrow} of {n_el} elements narrower than a lateral speckle cell)")


#: The fields of a volume's registration picture (three orthogonal slices each), in order.
VOLUME_KEYS = ("ux", "exx", "eyy", "ezz", "quality")


def plot_volume_result(args) -> int:
    """``femreg plot`` of a volume's registration result (``register`` / ``track`` on volumes): three orthogonal
    slices of u_x, e_xx, e_yy, e_zz and the quality (:func:`femreg.volplot.plot_volume_slices`) through
    ``--slice X Y Z`` (default: the centre of the registered box), a failed result's title saying so, and
    ``--vtu`` / ``--xdmf``.  Exit 1 for a failed result (the picture is written)."""
    import matplotlib.pyplot as plt
    import numpy as np

    from ..volplot import plot_volume_slices
    from ..volume_result import SweptResult, load_volume_result

    for flag in ("reference", "frame"):
        if getattr(args, flag, None) is not None:
            raise InputError(f"--{flag} draws a frame's B-mode beside a 2D result; a volume's result is drawn "
                             "without it")
    if args.overlay or args.shear or args.render or args.field != "exx":
        raise InputError("--overlay, --shear, --render and --field are options of a 2D result's picture; a "
                         "volume's draws u_x, e_xx, e_yy, e_zz and the quality")
    res = load_volume_result(args.result)
    if isinstance(res, SweptResult):    # the scan-converted Cartesian grid the result lives on
        grid, (_, spacing, origin) = res.cartesian_grid(), res.cartesian
    else:
        grid, spacing, origin = res.on_grid(), res.spacing, res.origin
    # the picture covers the registered box (the fields are NaN outside it: a depth cut left blank otherwise)
    lo, hi = res.mesh.p.min(axis=1), res.mesh.p.max(axis=1)
    sp, org = np.asarray(spacing, float), np.asarray(origin, float)
    n = np.asarray(next(iter(grid.values())).shape)
    i0 = np.clip(np.floor((lo - org) / sp).astype(int), 0, n - 1)
    i1 = np.clip(np.ceil((hi - org) / sp).astype(int) + 1, i0 + 1, n)
    box = tuple(slice(a, b) for a, b in zip(i0, i1))
    grid = {k: v[box] for k, v in grid.items() if np.ndim(v) == 3}
    origin = tuple(float(v) for v in org + i0 * sp)
    at = getattr(args, "slice", None)
    if at is None or list(at) == ["centre"]:
        at = tuple(float(v) for v in 0.5 * (lo + hi))
    else:
        try:
            at = tuple(float(v) for v in at)
        except ValueError:
            at = ()
        if len(at) != 3:
            raise InputError(f"--slice of a volume's result takes X Y Z (mm) or centre, got {' '.join(args.slice)}")
    # the title names the voxel centres the panels show (femreg.volplot snaps each slice to the nearest voxel)
    at = tuple(float(o + round((a - o) / d) * d) for a, o, d in zip(at, origin, sp))
    ok = bool(getattr(res, "success", True))
    title = f"{Path(args.result).name}: slices through x, y, z = {at[0]:.1f}, {at[1]:.1f}, {at[2]:.1f} mm"
    if not ok:
        why = str(res.message or "")
        title = f"{why if why.startswith('FAILED') else 'FAILED: ' + why} -- {title}"
    out = Path(args.output) if args.output else Path(args.result).with_suffix(".png")
    fig = plot_volume_slices(grid, spacing, origin, keys=[k for k in VOLUME_KEYS if k in grid], at=at,
                             out_png=out, title=title, dpi=args.dpi)
    plt.close(fig)
    print(f"wrote {out}")
    if args.vtu:
        res.write_vtu(args.vtu)
        print(f"wrote {args.vtu}")
    if args.xdmf:
        res.write_xdmf(args.xdmf)
        print(f"wrote {args.xdmf}")
    return 0 if ok else 1
