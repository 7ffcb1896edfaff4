"""3D against 2D registration on the paper's 3D phantom imaged as RF volumes.

The paper's 3D FE model (HI by default: the 4x stiffer 15 mm sphere, 30 mm deep) imaged as volumes covering its
imaged plane (72 mm deep x 44 mm lateral) and +-10 mm elevationally (``forward.volume.paper_volume_sequence``:
the paper's 5.5 MHz PSF and 40 MHz / 0.3 mm sampling, a 2 mm elevational beam on 0.5 mm planes, 12 dB SNR,
cached), frames 1 -> 7 of its compression schedule (0.8 % mean axial strain).

* 2D: ``femreg.register`` on the central plane (z = 0) of both volumes, as the paper registers its 2D frames.
* 3D: ``femreg.register`` on the volumes with ``spacing=(dx, dy, dz)``, where the installed femreg registers
  volumes (otherwise the script says so).

Errors against the exact FE truth (``forward.volume.FEVolumeField``), with femreg.metrics' formulas so that the
numbers compare with docs/study_report.md: on the central plane, integrated with the 2D registration mesh's
quadrature (the same domain and weights for both), relative L2 errors of u_x, u_y and of the in-plane strains and
the in-plane total strain (e_xy counted twice); for 3D also u_z and the six-component total strain over the
interior of the volume (2 mm margin), which 2D cannot measure.

Run: ``python benchmarks/volume_study.py [--inclusion HI] [--crop X0 X1 Y0 Y1 Z0 Z1] [--quick] [--json FILE]``.
``--quick`` crops to 20-42 mm deep, +-11 mm lateral and +-5 mm elevational around the inclusion (the crop also
applies to the 2D plane).  The first run renders and caches the volumes (minutes; about 1.8 M scatterers).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import femreg  # noqa: E402
from femreg import metrics as M  # noqa: E402
from femreg.errors import InputError  # noqa: E402
from forward.volume import STRAIN_COMPONENTS_3D, paper_volume_sequence  # noqa: E402

IN_PLANE = [0, 1, 3]          # exx, eyy, exy of the six 3D components


def crop(seq, box):
    """Voxel slices and origin of ``box`` = (x0, x1, y0, y1, z0, z1) mm (None: everything)."""
    g = seq.grid
    if box is None:
        return (slice(None),) * 3, g.origin
    sl = []
    for a in range(3):
        c = g.axis(a)
        idx = np.flatnonzero((c >= box[2 * a] - 1e-9) & (c <= box[2 * a + 1] + 1e-9))
        if idx.size < 4:
            raise InputError(f"crop {box} leaves {idx.size} samples along axis {a}")
        sl.append(slice(int(idx[0]), int(idx[-1]) + 1))
    return tuple(sl), tuple(float(g.axis(a)[s.start]) for a, s in enumerate(sl))


def plane_truth(field):
    """In-plane true displacement and strain callables (n, 2) -> (n, 2), (n, 3) at z = 0."""
    def p3(p):
        p = np.asarray(p, float)
        return np.column_stack([p, np.zeros(len(p))])

    return (lambda p: field.displacement(p3(p))[:, :2]), (lambda p: field.strain(p3(p))[:, IN_PLANE])


def plane_errors_3d(res3, res2, field) -> dict:
    """femreg.metrics' relative errors of the 3D result on the central plane, at the 2D mesh's quadrature points."""
    pts, w, _ = M.mesh_quadrature(res2.mesh)
    q = np.column_stack([pts, np.zeros(len(pts))])
    um, em = np.asarray(res3.displacement(q), float), np.asarray(res3.strain(q), float)
    ok = np.all(np.isfinite(um), axis=1) & np.all(np.isfinite(em), axis=1)
    ut, et = field.displacement(q), field.strain(q)
    err = M._relative_errors(w[ok], um[ok, :2], ut[ok, :2], em[ok][:, IN_PLANE], et[ok][:, IN_PLANE])
    return {k: 100.0 * v for k, v in err.items()}


def volume_errors_3d(res3, seq, k, sl, origin, margin_mm=2.0) -> dict:
    """u_z and the six-component total strain (shear twice) over the interior voxels, relative L2 in %."""
    grid = res3.on_grid()
    g = seq.grid
    axes = [g.axis(a)[s] for a, s in enumerate(sl)]
    inner = [np.flatnonzero((c >= c[0] + margin_mm) & (c <= c[-1] - margin_mm)) for c in axes]
    X, Y, Z = np.meshgrid(*(c[i] for c, i in zip(axes, inner)), indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    ix = np.ix_(*inner)
    uz = grid["uz"][ix].ravel()
    em = np.column_stack([grid[c][ix].ravel() for c in STRAIN_COMPONENTS_3D])
    ut, et = seq.true_displacement(k, P), seq.true_strain(k, P)
    ok = np.isfinite(uz) & np.all(np.isfinite(em), axis=1)
    wt = np.array([1, 1, 1, 2, 2, 2], float)
    return {"uz": 100.0 * float(np.linalg.norm(uz[ok] - ut[ok, 2]) / np.linalg.norm(ut[ok, 2])),
            "e6": 100.0 * float(np.sqrt(np.sum(wt * (em[ok] - et[ok]) ** 2) / np.sum(wt * et[ok] ** 2))),
            "interior_voxels": int(ok.sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inclusion", default="HI", choices=("HI", "mHI", "HOM", "SI"))
    ap.add_argument("--crop", type=float, nargs=6, metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"))
    ap.add_argument("--quick", action="store_true", help="crop 20-42 x +-11 x +-5 mm around the inclusion")
    ap.add_argument("--regularizer", default="momentum-stress")
    ap.add_argument("--no-3d", action="store_true", help="the 2D registration only")
    ap.add_argument("--json", type=Path, help="write the numbers here")
    args = ap.parse_args(argv)
    box = args.crop or ((20.0, 42.0, -11.0, 11.0, -5.0, 5.0) if args.quick else None)

    t0 = time.perf_counter()
    seq = paper_volume_sequence(args.inclusion, frames=(0, 6), verbose=True)
    print(f"volumes {seq.frames.shape} (frames, axial, lateral, elevational), spacing {seq.spacing} mm, "
          f"{seq.params['n_scatterers']} scatterers, {time.perf_counter() - t0:.1f} s (cache: {seq.path})")
    sl, origin = crop(seq, box)
    ref, mov = (np.asarray(seq.frames[i][sl], np.float64) for i in (0, 1))
    field = seq.fields[1]
    k0 = int(np.argmin(np.abs(seq.grid.z[sl[2]])))
    z0 = float(seq.grid.z[sl[2]][k0])
    if abs(z0) > 1e-9:
        raise InputError(f"no elevational plane at z = 0 (nearest {z0:g} mm)")
    out = {"inclusion": args.inclusion, "crop_mm": box, "shape": list(ref.shape), "spacing": list(seq.spacing),
           "regularizer": args.regularizer, "mean_axial_strain": seq.params["strain_schedule"][-1]}

    # 2D: the central plane, as the paper
    t0 = time.perf_counter()
    res2 = femreg.register(ref[:, :, k0], mov[:, :, k0], spacing=seq.spacing[:2], origin=origin[:2],
                           regularizer=args.regularizer)
    t2 = time.perf_counter() - t0
    tu, te = plane_truth(field)
    e2 = {k: 100.0 * v for k, v in M.field_errors(res2, tu, te).items()}
    out["2d"] = dict(e2, time_s=t2, success=bool(res2.success), message=res2.message)
    print(f"2D central plane ({args.regularizer}): {t2:.1f} s, success {res2.success}")
    # 3D, where femreg registers volumes
    if not args.no_3d:
        try:
            t0 = time.perf_counter()
            res3 = femreg.register(ref, mov, spacing=seq.spacing, origin=origin, regularizer=args.regularizer)
            t3 = time.perf_counter() - t0
        except InputError as exc:
            if "2D" not in str(exc):
                raise
            print(f"3D registration: not available in this femreg ({exc})")
            out["3d"] = None
        else:
            e3 = plane_errors_3d(res3, res2, field)
            e3.update(volume_errors_3d(res3, seq, 1, sl, origin))
            out["3d"] = dict(e3, time_s=t3, success=bool(res3.success), message=res3.message)
            print(f"3D volumes ({args.regularizer}): {t3:.1f} s, success {res3.success}")

    rows = [("u_x", "ux"), ("u_y", "uy"), ("u_z", "uz"), ("e_xx", "exx"), ("e_yy", "eyy"), ("e_xy", "exy"),
            ("in-plane total strain", "e"), ("six-component strain (volume)", "e6")]
    print(f"\nerrors against the exact FE truth, frames 1 -> 7 ({100 * out['mean_axial_strain']:.2f} % mean axial "
          f"strain), %:")
    print(f"  {'':32s} {'2D':>8s} {'3D':>8s}")
    for label, key in rows:
        a = out["2d"].get(key)
        b = (out.get("3d") or {}).get(key)
        fmt = lambda v: f"{v:8.2f}" if v is not None else f"{'-':>8s}"  # noqa: E731
        print(f"  {label:32s} {fmt(a)} {fmt(b)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2, default=str))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
