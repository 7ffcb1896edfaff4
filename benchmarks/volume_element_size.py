"""Element size and alpha on crops of the paper's 3D phantom (HI, frames 1 -> 7, as benchmarks/volume_study.py):
the in-plane total strain error on the central plane of the 2D and 3D registrations and of the truth put on
the mesh nodes (the floor), over the whole crop mesh and over its interior (``--margin-eval`` mm, default 3, from
the crop's edges), for one element size, one alpha factor and one iteration limit per run.

``--alpha-factor F``: alpha = F x femreg's default momentum-stress alpha (for 2 x 2 (x 2) mm elements; femreg
rescales it by element area / volume as always, so F = 1/8 on 1 mm hexahedra keeps the 2 mm weight).  Prints one
``ROW {json}`` line; the rows behind the findings of docs/study_report.md's 3D section are in
paperstudy/volume_runs/element_size_sweep.jsonl.

    python benchmarks/volume_element_size.py --h 1 --alpha-factor 0.125 [--crop X0 X1 Y0 Y1 Z0 Z1] [--no2d]
"""
import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import femreg  # noqa: E402
import volume_study as VS  # noqa: E402
from femreg import metrics as M  # noqa: E402
from forward.volume import paper_volume_sequence  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--crop", type=float, nargs=6, default=[20, 42, -11, 11, -5, 5])
ap.add_argument("--h", type=float, nargs="+", default=[2.0])
ap.add_argument("--alpha-factor", type=float, default=1.0)
ap.add_argument("--maxiter", type=int, default=20)
ap.add_argument("--no2d", action="store_true")
ap.add_argument("--no3d", action="store_true")
ap.add_argument("--margin-eval", type=float, default=3.0)
a = ap.parse_args()
seq = paper_volume_sequence("HI", frames=(0, 6))
box = None if a.crop[0] < 0 else a.crop
sl, origin = VS.crop(seq, box)
ref, mov = (np.asarray(seq.frames[i][sl], np.float64) for i in (0, 1))
field = seq.fields[1]
k0 = int(np.argmin(np.abs(seq.grid.z[sl[2]])))
hs = a.h * 3 if len(a.h) == 1 else a.h
from femreg.strategy import effective_regularizer_options, fresh_regularizer  # noqa: E402
A0 = fresh_regularizer("momentum-stress", None,
                       effective_regularizer_options("auto", "momentum-stress", None)).alpha * a.alpha_factor
tu, te = VS.plane_truth(field)

def errs(res, mesh2, dim):
    pts, w, _ = M.mesh_quadrature(mesh2)
    lo, hi = pts.min(0), pts.max(0)
    q = pts if dim == 2 else np.column_stack([pts, np.zeros(len(pts))])
    um, em = np.asarray(res.displacement(q), float), np.asarray(res.strain(q), float)
    ut, et = field.displacement(np.column_stack([pts, np.zeros(len(pts))])), field.strain(np.column_stack([pts, np.zeros(len(pts))]))
    um, em = um[:, :2], (em if dim == 2 else em[:, VS.IN_PLANE])
    ut, et = ut[:, :2], et[:, VS.IN_PLANE]
    out = {}
    inner = np.all((pts >= lo + a.margin_eval) & (pts <= hi - a.margin_eval), axis=1)
    for name, m in (("all", np.ones(len(pts), bool)), ("inner", inner)):
        ok = m & np.all(np.isfinite(um), 1) & np.all(np.isfinite(em), 1)
        e = M._relative_errors(w[ok], um[ok], ut[ok], em[ok], et[ok])
        out[name] = {k: round(100 * v, 2) for k, v in e.items() if k in ("uy", "exx", "eyy", "exy", "e")}
    return out

row = {"crop": box, "h": hs, "alpha_factor": a.alpha_factor, "maxiter": a.maxiter, "shape": list(ref.shape)}
t = time.perf_counter()
res2 = femreg.register(ref[:, :, k0], mov[:, :, k0], spacing=seq.spacing[:2], origin=origin[:2],
                       element_size=tuple(hs[:2]), alpha=A0, maxiter=a.maxiter)
floor2 = femreg.RegistrationResult(res2.mesh, M.interpolate_truth(res2.mesh, tu), shape=ref.shape[:2],
                                   spacing=seq.spacing[:2], origin=origin[:2])
if not a.no2d:
    row["2d"] = errs(res2, res2.mesh, 2); row["2d_floor"] = errs(floor2, res2.mesh, 2)
    row["2d_nit"] = res2.nit; row["2d_msg"] = res2.message[:90]; row["2d_s"] = round(time.perf_counter() - t, 1)
if not a.no3d:
    t, c = time.perf_counter(), time.process_time()
    res3 = femreg.register(ref, mov, spacing=seq.spacing, origin=origin, element_size=tuple(hs), alpha=A0,
                           maxiter=a.maxiter)
    row["3d_s"], row["3d_cpu"] = round(time.perf_counter() - t, 1), round(time.process_time() - c, 1)
    floor3 = femreg.VolumeResult(res3.mesh, field.displacement(res3.mesh.p.T).ravel(), shape=ref.shape,
                                 spacing=seq.spacing, origin=origin)
    row["3d"] = errs(res3, res2.mesh, 3); row["3d_floor"] = errs(floor3, res2.mesh, 3)
    row["3d_nit"] = res3.nit; row["3d_msg"] = res3.message[:90]; row["3d_success"] = res3.success
    row["3d_energy"] = [round(float(v), 4) for v in res3.energy_history]
row["maxrss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
print("ROW", json.dumps(row))
