"""Benchmark and mesh-convergence study of the forward models (issue 2).

Prints, per model and mesh size: DOFs, mesh / assembly / solve time, peak RSS, reaction force, and for the
imaging plane the axial strain e_xx on the imaged area (44 mm lateral x 72 mm axial from the top, 0.25 mm grid):
relative L2 difference to the next finer mesh, with and without a 1 mm band around the inclusion boundary (where
the polygonal interface of different meshes sits at slightly different places).  Also times point evaluation on a
paper-size pixel grid (3750 x 147 = 0.55 M points).

Usage: python benchmarks/bench_forward.py [--quick] [--models 3d,plane-strain] [--sizes 2,1.5,1]
Each solve runs in a fresh subprocess so that the peak memory figure belongs to that solve alone.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def grid(step=0.25):
    x = np.arange(0.0, 72.0 + 1e-9, step)
    y = np.arange(-22.0, 22.0 + 1e-9, step)
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.c_[X.ravel(), Y.ravel()]


def one(model, h, coarse, out):
    """Child process: solve, evaluate, dump exx on the grid and info."""
    sys.path.insert(0, str(ROOT))
    import forward
    kw = {} if coarse is None else {"coarse_size_mm": coarse}
    sol = forward.solve_elasticity(model, mesh_size_mm=h, **kw)
    P = grid()
    t = time.perf_counter()
    e = sol.strain(P)
    t_eval_grid = time.perf_counter() - t
    x = np.linspace(0, 72, 3750)
    y = np.linspace(-22, 22, 147)
    X, Y = np.meshgrid(x, y, indexing="ij")
    PP = np.c_[X.ravel(), Y.ravel()]
    t = time.perf_counter()
    sol.strain(PP)
    sol.displacement(PP)
    t_eval = time.perf_counter() - t
    import resource
    info = dict(sol.info, eval_pixels_s=t_eval, eval_grid_s=t_eval_grid,
                peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    np.savez(out, exx=e[:, 0], info=json.dumps(info))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse meshes only")
    ap.add_argument("--models", default="3d,plane-strain,plane-stress")
    ap.add_argument("--sizes", default=None, help="comma-separated fine mesh sizes, coarse to fine (mm)")
    ap.add_argument("--coarse", type=float, default=None, help="far-field element size (mm); default per model")
    ap.add_argument("--_child", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a._child:
        model, h, coarse, out = a._child
        one(model, float(h), None if coarse == "None" else float(coarse), out)
        return 0
    import tempfile
    tmp = Path(tempfile.mkdtemp(prefix="bench_forward_"))
    P = grid()
    r = np.hypot(P[:, 0] - 30.0, P[:, 1])
    band = np.abs(r - 7.5) > 1.0
    for model in a.models.split(","):
        if a.sizes:
            sizes = [float(s) for s in a.sizes.split(",")]
        elif model == "3d":
            sizes = [3.0, 2.0] if a.quick else [2.0, 1.5, 1.0]
        else:
            sizes = [2.0, 1.0] if a.quick else [1.5, 0.75, 0.375]
        print(f"== {model}")
        print(f"{'h mm':>6} {'DOFs':>9} {'mesh s':>7} {'asm s':>7} {'solve s':>8} {'total s':>8} {'peak MB':>8} "
              f"{'reaction':>10} {'eval 0.55M s':>12} {'exx(30,0)':>11}")
        fields = []
        for h in sizes:
            out = tmp / f"{model}-{h}.npz"
            t = time.perf_counter()
            subprocess.run([sys.executable, __file__, "--_child", model, str(h), str(a.coarse), str(out)],
                           check=True)
            with np.load(out) as z:
                exx, info = z["exx"], json.loads(str(z["info"]))
            fields.append(exx)
            centre = exx[np.argmin(np.hypot(P[:, 0] - 30, P[:, 1]))]
            print(f"{h:6.3g} {info['n_dofs']:9d} {info['mesh_time_s']:7.1f} {info['assembly_time_s']:7.1f} "
                  f"{info['solve_time_s']:8.1f} {info['total_time_s']:8.1f} {info['peak_rss_mb']:8.0f} "
                  f"{info['reaction_force']:10.3f} {info['eval_pixels_s']:12.2f} {centre:11.5f}", flush=True)
            if len(fields) > 1:
                d = fields[-2] - fields[-1]
                print(f"       e_xx over the imaged area vs previous mesh: rel. L2 diff "
                      f"{np.linalg.norm(d) / np.linalg.norm(fields[-1]):.2%} (outside 1 mm interface band: "
                      f"{np.linalg.norm(d[band]) / np.linalg.norm(fields[-1][band]):.2%})", flush=True)
        for i in range(len(sizes) - 1):
            d = fields[i] - fields[-1]
            rel = np.linalg.norm(d) / np.linalg.norm(fields[-1])
            relb = np.linalg.norm(d[band]) / np.linalg.norm(fields[-1][band])
            dn = fields[i] - fields[i + 1]
            reln = np.linalg.norm(dn) / np.linalg.norm(fields[i + 1])
            print(f"imaging-plane e_xx, h={sizes[i]:g} vs h={sizes[i + 1]:g}: rel. L2 diff {reln:.2%};"
                  f" vs finest h={sizes[-1]:g}: {rel:.2%} (outside 1 mm interface band: {relb:.2%})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
