"""Swept-probe volumes against Cartesian volumes of the same field: total strain error over the interior.

A swept pair (``forward.swept.make_swept_pair``: a linear or convex array rocked in elevation, rendered along its
fan frames) is registered with ``femreg.register(..., geometry=femreg.Swept(...))`` (scan-converted inside the fan,
:mod:`femreg.swept`); the Cartesian pair (``forward.volume.make_volume_pair``: the same probe's PSF on its
Cartesian voxel grid, the same field) covers the swept pair's registered box.  Both are scored on the same points:
a lattice over the swept result's mesh box less ``--margin`` mm, total strain error = relative L2 of the six
strain components with the shears counted twice.  Fields: an affine compression (1 %) with shears (xy 0.3 %,
xz 0.5 %), and the paper's 3D stiff sphere (15 mm, 4x stiffer, at 30 mm depth; the cached 3D FE solution scaled
to 1 % mean axial strain over the box).  Two seeds each.

    python benchmarks/swept_volume.py [--cases affine sphere] [--seeds 0 1] [--json rows.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])


def total_strain_error(res, field, lo, hi, n=16) -> tuple:
    """(error %, fraction of the points inside the result's mesh) on an n^3 lattice of the box [lo, hi]."""
    ax = [np.linspace(lo[a], hi[a], n) for a in range(3)]
    P = np.column_stack([g.ravel() for g in np.meshgrid(*ax, indexing="ij")])
    est, true = res.strain(P), np.asarray(field.strain(P), float)
    ok = np.all(np.isfinite(est), axis=1) & np.all(np.isfinite(true), axis=1)
    err = np.sqrt(np.sum(WEIGHTS * (est[ok] - true[ok]) ** 2) / np.sum(WEIGHTS * true[ok] ** 2))
    return float(100.0 * err), float(np.mean(ok))


def sphere_field(lo, hi):
    """The paper's 3D HI phantom's unit-compression FE field scaled to 1 % mean axial strain over [lo, hi]."""
    from forward.elasticity import cached_solve
    from forward.sequences import BACKGROUND_MODULUS, INCLUSIONS
    from forward.volume import FEVolumeField

    sol = cached_solve("3d", inclusion_modulus=INCLUSIONS["HI"], background_modulus=BACKGROUND_MODULUS,
                       inclusion_depth_mm=30.0, inclusion_diameter_mm=15.0, compression_mm=1.0)
    unit = FEVolumeField(sol, 1.0, name="3d-HI")
    ax = [np.linspace(lo[a], hi[a], 9) for a in range(3)]
    P = np.column_stack([g.ravel() for g in np.meshgrid(*ax, indexing="ij")])
    s = 0.01 / -float(np.nanmean(unit.strain(P)[:, 0]))
    return FEVolumeField(sol, s, name=f"3d-HI x{s:.3f}")


CASES = {
    # name: (geometry kwargs, probe, depth, top, lines, frames)
    "affine-linear": (dict(sweep_radius_mm=20.0, angle_step_deg=1.0), "matrix7", 14.0, 3.0, 56, 25),
    "affine-convex": (dict(sweep_radius_mm=30.0, angle_step_deg=1.0, array=dict(kind="convex", radius_mm=40.0,
                                                                                 angle_pitch_deg=0.4)),
                      "matrix7", 14.0, 3.0, 41, 25),
    "sphere-linear": (dict(sweep_radius_mm=20.0, angle_step_deg=1.0), "paper3d", 24.0, 18.0, 84, 31),
}


def run(case, seed, grid_spacing=None):
    import femreg
    from forward.swept import make_swept_pair
    from forward.volume import Affine3D, make_volume_pair

    gkw, probe, depth, top, n_lines, n_frames = CASES[case]
    geo = femreg.Swept(**gkw)
    if case.startswith("affine"):
        field = Affine3D(0.01, shear={"xy": 0.003, "xz": 0.005}, centre=(top + 0.5 * depth, 0.0, 0.0))
    else:
        field = sphere_field(np.array([top + 2, -6.0, -5.0]), np.array([top + depth - 2, 6.0, 5.0]))
    p = make_swept_pair(field, geo, probe, depth_mm=depth, n_lines=n_lines, n_frames=n_frames, top_mm=top,
                        seed=seed)
    t = time.process_time()
    rs = femreg.register(p.ref, p.mov, spacing=p.spacing, origin=p.origin, geometry=geo, grid_spacing=grid_spacing)
    ts = time.process_time() - t
    lo, hi = rs.mesh.p.min(axis=1), rs.mesh.p.max(axis=1)
    # the Cartesian pair over the swept result's mesh box + 1 mm
    size = tuple(float(v) for v in (hi - lo + 2.0))
    c = make_volume_pair(field, probe, (size[0], 2 * max(abs(lo[1]), abs(hi[1])) + 2.0,
                                        2 * max(abs(lo[2]), abs(hi[2])) + 2.0), top_mm=float(lo[0] - 1.0), seed=seed)
    t = time.process_time()
    rc = femreg.register(c.ref, c.mov, spacing=c.spacing, origin=c.origin)
    tc = time.process_time() - t
    m = ARGS.margin
    es, fs = total_strain_error(rs, field, lo + m, hi - m)
    ec, fc = total_strain_error(rc, field, lo + m, hi - m)
    row = dict(case=case, seed=seed, swept_error=es, swept_cover=fs, swept_cpu_s=ts, swept_success=rs.success,
               cartesian_error=ec, cartesian_cover=fc, cartesian_cpu_s=tc, cartesian_success=rc.success,
               swept_shape=list(p.ref.shape), scan_converted=list(rs.cartesian[0]),
               grid_spacing=[float(v) for v in rs.cartesian[1]], cartesian_shape=list(c.ref.shape),
               box=[float(v) for v in np.ravel([lo, hi])], excluded=rs.excluded)
    print(f"| {case} | {seed} | {es:.2f} % ({ts:.0f} s{'' if rs.success else ', FAILED'}) | "
          f"{ec:.2f} % ({tc:.0f} s{'' if rc.success else ', FAILED'}) | {tuple(p.ref.shape)} -> "
          f"{tuple(rs.cartesian[0])} @ {', '.join(f'{v:.3g}' for v in rs.cartesian[1])} mm |", flush=True)
    return row


def main(argv=None):
    global ARGS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--margin", type=float, default=1.0, help="interior: the mesh box less this, mm")
    ap.add_argument("--grid", nargs=2, type=float, default=None, help="lateral, elevational grid spacing mm")
    ap.add_argument("--json", default=None)
    ARGS = ap.parse_args(argv)
    print("| case | seed | swept (CPU) | Cartesian (CPU) | samples -> voxels @ spacing |\n|---|---|---|---|---|")
    rows = [run(c, s, ARGS.grid) for c in ARGS.cases for s in ARGS.seeds]
    if ARGS.json:
        Path(ARGS.json).write_text(json.dumps(rows, indent=1))


ARGS = None

if __name__ == "__main__":
    main()
