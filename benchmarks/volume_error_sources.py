"""Where the 3D registration's in-plane strain error sits on the paper's 3D phantom (HI, frames 1 -> 7).

The in-plane total strain error of ``benchmarks/volume_study.py`` (relative L2 of e_xx, e_yy, e_xy with e_xy
counted twice, on the central plane z = 0 at the quadrature points of femreg's default 2D mesh of that plane),
split by strain component and by region of the plane: inside the sphere (r < R - ``--shell``), its boundary
shell (|r - R| <= ``--shell``, default 1.5 mm), the background out to 7.5 mm beyond the sphere ("near") and the
rest; each part as 100 sqrt(its squared error / the truth's squared norm), so that the parts' squares add up
to the total's square.  The same split for the mesh's floor (the exact displacement at the mesh's nodes, its
strain recovered the same way) and for the registered field minus that floor (what the registration adds).

Run: ``python benchmarks/volume_error_sources.py [--element-size H ...] [--refine auto|off|key=value,...]
[--alpha-3d A] [--linear-solver S] [--axes-npz AXES.npz [--alpha-factor F]] [--save U.npz | --load U.npz]
[--floor-only] [--strain recovered|element|linear] [--quadrature Q.npz] [--refined-weight F]``.  ``--floor-only`` scores the truth on
the mesh the options give (no images; seconds); ``--axes-npz`` registers on (or scores) the tensor mesh of the
node axes ``ax``, ``ay``, ``az`` in that file, with the default 2 mm mesh's weight of eq:objf kept
(:func:`femreg.scaling.refined_alpha`); ``--save`` keeps the registered nodal field and its mesh axes, ``--load``
scores a saved one; ``--strain linear`` recovers the nodal strains by linear interpolation of the element-centre
ones along each axis instead of femreg's plain average; ``--refined-weight F`` multiplies the weight of eq:objf
of the refinement's solves by F (femreg keeps the unrefined mesh's, :func:`femreg.scaling.refined_alpha`).
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import femreg  # noqa: E402
from femreg import metrics as M  # noqa: E402

from volume_study import CENTRE, IN_PLANE, RADIUS, _refine_arg  # noqa: E402

#: The background within this many mm of the sphere ("near") is scored apart from the rest.
NEAR_MM = 7.5
W3 = np.array([1.0, 1.0, 2.0])          # e_xx, e_yy, e_xy (shear twice)


def linear_recovery(mesh, u):
    """Nodal strains (n_nodes, 6) of a tensor hexahedral mesh interpolated linearly, axis by axis, from the
    element-centre strains (exact for a linear strain on a graded mesh, where the plain nodal average is not);
    boundary nodes take their cell's value."""
    from femreg.volume_fields import element_strains_3d
    from femreg.voxels import _cell_index, tensor_axes_3d

    axes, node = tensor_axes_3d(mesh)
    cell = _cell_index(mesh, node)
    C = element_strains_3d(mesh, u)[cell]                       # (n_x - 1, n_y - 1, n_z - 1, 6)
    for a in range(3):
        h = np.diff(axes[a])
        C = np.moveaxis(C, a, 0)
        out = np.empty((h.size + 1,) + C.shape[1:])
        out[0], out[-1] = C[0], C[-1]
        w = (h[1:] / (h[:-1] + h[1:])).reshape((-1,) + (1,) * (C.ndim - 1))  # weight of the cell before the node
        out[1:-1] = w * C[:-1] + (1 - w) * C[1:]
        C = np.moveaxis(out, 0, a)
    N = np.empty((mesh.p.shape[1], 6))
    N[node.ravel()] = C.reshape(-1, 6)
    return N


def strain_at(res, q, mode):
    """In-plane strains (n, 3) of a VolumeResult at q: femreg's recovered / element strain, or 'linear'."""
    if mode == "linear":
        res._nodal_strain = linear_recovery(res.mesh, res.u)
        mode = "recovered"
    return np.asarray(res.strain(q, strain=mode), float)[:, IN_PLANE]


def regions(q, shell):
    """Masks of the quadrature points (n, 2): inside the sphere's central disc less ``shell``, the shell
    ``|r - R| <= shell``, the background up to :data:`NEAR_MM` beyond the sphere ("near"), the rest."""
    r = np.hypot(q[:, 0] - CENTRE[0], q[:, 1] - CENTRE[1])
    band = np.abs(r - RADIUS) <= shell
    near = (r > RADIUS + shell) & (r <= RADIUS + NEAR_MM)
    return {"inside": (r < RADIUS) & ~band, "shell": band, "near": near, "background": r > RADIUS + NEAR_MM}


def split(w, em, et, masks) -> dict:
    """Total in-plane strain error % and, per region and component, the part of it: 100 sqrt(part / norm), so
    the parts' squares add up to the total's."""
    d2 = w[:, None] * W3 * (em - et) ** 2
    den = float(np.sum(w[:, None] * W3 * et ** 2))
    out = {"e": 100 * np.sqrt(d2.sum() / den)}
    for name, m in masks.items():
        out[name] = {c: 100 * np.sqrt(d2[m, i].sum() / den) for i, c in enumerate(("exx", "eyy", "exy"))}
        out[name]["all"] = 100 * np.sqrt(d2[m].sum() / den)
        out[name]["area_%"] = 100 * float(w[m].sum() / w.sum())
    out["components"] = {c: 100 * np.sqrt(d2[:, i].sum() / den) for i, c in enumerate(("exx", "eyy", "exy"))}
    return out


def show(title, s):
    print(f"{title}: in-plane total strain error {s['e']:.2f} %  (components: "
          + ", ".join(f"{k} {v:.2f}" for k, v in s["components"].items()) + ")")
    for name in ("inside", "shell", "near", "background"):
        v = s[name]
        print(f"    {name:10s} ({v['area_%']:5.1f} % of the plane): {v['all']:5.2f}  = exx {v['exx']:5.2f}, "
              f"eyy {v['eyy']:5.2f}, exy {v['exy']:5.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--element-size", type=float, nargs="+")
    ap.add_argument("--refine")
    ap.add_argument("--alpha-3d", type=float)
    ap.add_argument("--linear-solver", default="auto")
    ap.add_argument("--strain", default="recovered", choices=("recovered", "element", "linear"))
    ap.add_argument("--shell", type=float, default=1.5, help="half width mm of the sphere's boundary shell")
    ap.add_argument("--save", type=Path)
    ap.add_argument("--load", type=Path)
    ap.add_argument("--floor-only", action="store_true")
    ap.add_argument("--axes-npz", type=Path, help="score the floor on the node axes saved in this file")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--alpha-factor", type=float, default=1.0, help="with --axes-npz: times the kept 2 mm weight")
    ap.add_argument("--quadrature", type=Path, help="cache of the 2D scoring points (written when missing)")
    ap.add_argument("--refined-weight", type=float, default=1.0,
                    help="times the weight of eq:objf of the refined solves (femreg keeps the unrefined mesh's)")
    args = ap.parse_args(argv)
    if args.refined_weight != 1.0:
        # the refinement stage asks femreg.scaling.refined_alpha for the refined mesh's alpha (femreg.volume)
        import femreg.scaling as scaling

        kept = scaling.refined_alpha

        def refined_alpha(alpha, base, mesh, _kept=kept, _f=args.refined_weight):
            return _kept(alpha, base, mesh) * (_f if mesh is not base else 1.0)
        scaling.refined_alpha = refined_alpha

    from forward.volume import paper_volume_sequence
    from femreg.voxels import roi_mesh_3d
    from skfem import MeshHex1

    seq = paper_volume_sequence("HI", frames=(0, 6))
    field = seq.fields[1]
    k0 = int(np.argmin(np.abs(seq.grid.z)))
    origin = seq.grid.origin
    need_images = not (args.floor_only or args.load)
    ref = np.asarray(seq.frames[0], np.float64) if need_images else None
    mov = np.asarray(seq.frames[1], np.float64) if need_images else None
    # the scoring points: femreg's default 2D registration mesh of the central plane (as volume_study.py)
    if args.quadrature is not None and args.quadrature.is_file():
        z = np.load(args.quadrature)
        pts, w = z["pts"], z["w"]
    else:
        r2 = femreg.register(np.asarray(seq.frames[0][:, :, k0], float), np.asarray(seq.frames[1][:, :, k0], float),
                             spacing=seq.spacing[:2], origin=origin[:2], regularizer="momentum-stress")
        pts, w, _ = M.mesh_quadrature(r2.mesh)
        if args.quadrature is not None:
            np.savez(args.quadrature, pts=pts, w=w)
    q = np.column_stack([pts, np.zeros(len(pts))])
    et = field.strain(q)[:, IN_PLANE]
    masks = regions(pts, args.shell)
    hs = args.element_size
    hs = None if hs is None else (hs * 3 if len(hs) == 1 else hs)
    rec = {"options": vars(args) | {"save": str(args.save), "load": str(args.load), "json": str(args.json),
                                    "axes_npz": str(args.axes_npz),
                                    "quadrature": str(args.quadrature)}}

    res = None
    if args.load:
        z = np.load(args.load)
        mesh = MeshHex1.init_tensor(z["ax"], z["ay"], z["az"])
        res = femreg.VolumeResult(mesh, z["u"], shape=seq.frames.shape[1:], spacing=seq.spacing, origin=origin)
    elif args.floor_only:
        if args.axes_npz:
            z = np.load(args.axes_npz)
            mesh = MeshHex1.init_tensor(z["ax"], z["ay"], z["az"])
        else:
            mesh = roi_mesh_3d(seq.frames.shape[1:], seq.spacing, origin, element_size=hs)
    else:
        kw = {} if hs is None else {"element_size": tuple(hs)}
        if args.alpha_3d is not None:
            kw["alpha"] = args.alpha_3d
        if args.axes_npz:
            # a given mesh, the default 2 mm mesh's weight of eq:objf kept (femreg.scaling.refined_alpha)
            from femreg.regularizers import make_regularizer
            from femreg.scaling import refined_alpha
            z = np.load(args.axes_npz)
            kw["mesh"] = MeshHex1.init_tensor(z["ax"], z["ay"], z["az"])
            if args.alpha_3d is None:
                base = roi_mesh_3d(seq.frames.shape[1:], seq.spacing, origin)
                kw["alpha"] = args.alpha_factor * refined_alpha(make_regularizer("momentum-stress").alpha, base, kw["mesh"])
            rec["alpha"] = kw["alpha"]
        if args.refine is not None:
            kw["refine"] = _refine_arg(args.refine)
        t0, c0 = time.perf_counter(), time.process_time()
        res = femreg.register(ref, mov, spacing=seq.spacing, origin=origin, regularizer="momentum-stress",
                              linear_solver=args.linear_solver, **kw)
        rec["time_s"], rec["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        rec["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        rec["message"] = res.message
        mesh = res.mesh
        print(f"registered: {rec['time_s']:.1f} s wall, {rec['cpu_s']:.1f} s CPU, peak {rec['peak_rss_mb']:.0f} MB, "
              f"{mesh.t.shape[1]} elements; {res.message}")
        if args.save:
            from femreg.voxels import tensor_axes_3d
            ax = tensor_axes_3d(mesh)[0]
            np.savez(args.save, u=np.asarray(res.u), ax=ax[0], ay=ax[1], az=ax[2])
    rec["elements"] = int(mesh.t.shape[1])
    floor = femreg.VolumeResult(mesh, field.displacement(mesh.p.T).ravel(), shape=seq.frames.shape[1:],
                                spacing=seq.spacing, origin=origin)
    ef = strain_at(floor, q, args.strain)
    rec["floor"] = split(w, ef, et, masks)
    show(f"floor ({mesh.t.shape[1]} elements)", rec["floor"])
    if res is not None:
        em = strain_at(res, q, args.strain)
        rec["registered"] = split(w, em, et, masks)
        rec["registered_minus_floor"] = split(w, em, ef, masks) | {}
        show("registered", rec["registered"])
        # relative to the true strain's norm: what the registration adds on top of the floor's field
        d2 = w[:, None] * W3 * (em - ef) ** 2
        den = float(np.sum(w[:, None] * W3 * et ** 2))
        gap = {name: 100 * np.sqrt(d2[m].sum() / den) for name, m in masks.items()}
        rec["registration_vs_floor"] = gap
        print("    registered - floor (norm of the truth): " + ", ".join(f"{k} {v:.2f}" for k, v in gap.items()))
    if args.json:
        args.json.write_text(json.dumps(rec, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
