"""Benchmark of ``femreg.register`` on a paper-geometry pair (3750 x 147 pixels, dx 0.0192 mm, dy 0.3 mm).

The pair is synthetic (femreg.synthetic: PSF-convolved speckle, SNR 12 dB, warped by a known smooth field with
0.4-0.8 % axial compression); the real RF simulator lands later.  For every registered regulariser it prints the
time of each stage (block matching, operator build, regulariser set-up, each Gauss-Newton iteration, total) and
the peak memory (each regulariser runs in a fresh process so that ru_maxrss is its own).

    python benchmarks/bench_register.py                 # timings
    python benchmarks/bench_register.py --study         # alpha and element-size study (total strain error)
    python benchmarks/bench_register.py --solvers       # linear-solver comparison on the GN system

Measured 2026-11-21 on the shared 2-core machine (load average 5-7, fastest of 5), default 2 mm mesh (792 nodes):
total 1.0-1.7 s per pair for R_eps / R_eps_i, 1.9-2.2 s for the momentum regularisers (Hessian re-factorised
each iteration), peak RSS ~400 MB (120 MB of it the Python process, imports and the pair).  Where the time goes:
each Gauss-Newton iteration is ~0.1 s, dominated by the cubic-spline re-interpolation of I_2 at the 0.5 M pixels
(scipy map_coordinates, ~50-80 ms); block matching 0.1-0.2 s; operator build 0.12-0.15 s; the data Hessian is
assembled once by separable row/column sums (~0.03 s) and, for quadratic regularisers, factorised once.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SPACING = (0.0192, 0.3)
SHAPE = (3750, 147)


def paper_field(p):
    """Known displacement (mm): axial compression 0.4 % at the top rising to 0.8 % at the bottom, lateral
    expansion, plus a smooth inclusion-like bump 30 mm deep (non-affine)."""
    x, y = p[:, 0], p[:, 1]
    yc = 0.5 * (SHAPE[1] - 1) * SPACING[1]
    r2 = (x - 30.0) ** 2 + (y - yc) ** 2
    bump = np.exp(-r2 / (2 * 6.0 ** 2))
    ux = -(0.004 * x + 0.004 * x ** 2 / (2 * 72.0)) + 0.012 * bump
    uy = 0.003 * (y - yc) - 0.0015 * (y - yc) * bump
    return np.column_stack([ux, uy])


def make_pair(seed=0, snr_db=12.0):
    from femreg.synthetic import speckle_pair
    return speckle_pair(paper_field, SHAPE, SPACING, seed=seed, snr_db=snr_db)


def _run_one(name, alpha, element_size, q, repeat=1):
    import femreg
    from femreg.metrics import field_errors
    ref, mov = make_pair()
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    best = None
    for _ in range(repeat):   # the machine is shared: keep the fastest of `repeat` runs
        t = time.perf_counter()
        res = femreg.register(ref, mov, spacing=SPACING, regularizer=name, alpha=alpha,
                              element_size=element_size)
        total = time.perf_counter() - t
        if best is None or total < best[0]:
            best = (total, res)
    total, res = best
    err = field_errors(res, paper_field)
    q.put(dict(name=name, alpha=res.alpha, timings=res.timings, total=total, nit=res.nit, success=res.success,
               message=res.message, err=err, n_nodes=res.mesh.p.shape[1], ncc=(res.ncc_before, res.ncc_after),
               rss_before_mb=base / 1024, peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def run_isolated(name, alpha=None, element_size=None, repeat=1):
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_run_one, args=(name, alpha, element_size, q, repeat))
    p.start()
    out = q.get()
    p.join()
    return out


def timings():
    from femreg.regularizers import available_regularizers
    print(f"paper-geometry pair {SHAPE}, spacing {SPACING} mm, SNR 12 dB; fastest of 5 runs per regulariser")
    for name in available_regularizers():
        r = run_isolated(name, repeat=5)
        t = r["timings"]
        it = t["per_iteration"]
        print(f"\n[{name}] alpha={r['alpha']:g}  nodes={r['n_nodes']}  nit={r['nit']}  success={r['success']}  "
              f"({r['message']})")
        print(f"  prefilter {t['prefilter']:.3f} s | operator build {t['operator']:.3f} s | regulariser set-up "
              f"{t['regularizer_setup']:.3f} s | block matching {t['initial']:.3f} s")
        if it:
            print(f"  GN: first iteration {it[0]:.3f} s (incl. Hessian assembly + factorisation), "
                  f"later {np.mean(it[1:]) if len(it) > 1 else float('nan'):.3f} s/iter, "
                  f"GN total {t['gauss_newton']:.3f} s")
        print(f"  TOTAL {r['total']:.3f} s   peak RSS {r['peak_mb']:.0f} MB (after imports+pair {r['rss_before_mb']:.0f} MB)")
        e = r["err"]
        print(f"  errors: ux {100*e['ux']:.2f} %  uy {100*e['uy']:.1f} %  exx {100*e['exx']:.1f} %  "
              f"eyy {100*e['eyy']:.1f} %  exy {100*e['exy']:.1f} %  total strain {100*e['e']:.1f} %   "
              f"NCC {r['ncc'][0]:.3f} -> {r['ncc'][1]:.3f}")


def study(sizes=(1.0, 2.0), grids=None):
    """Total strain error over (element size, alpha) for R_eps and R_eps_i (frames 1 -> 2 of the synthetic pair)."""
    grids = grids or {"strain": [1.0, 10.0, 30.0, 100.0, 300.0, 1e3, 3e3, 1e4],
                      "strain-incompressible": [0.1, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0]}
    for name, alphas in grids.items():
        for h in sizes:
            print(f"\n[{name}] element {h} mm: alpha sweep (errors in %)", flush=True)
            for a in alphas:
                r = run_isolated(name, a, h)
                e = r["err"]
                print(f"  alpha {a:8.1e}: total strain {100*e['e']:6.1f}  exx {100*e['exx']:6.1f}  "
                      f"eyy {100*e['eyy']:6.1f}  exy {100*e['exy']:6.1f}  ux {100*e['ux']:5.2f}  uy {100*e['uy']:6.1f}"
                      f"  nit {r['nit']:2d}  {r['total']:.2f} s", flush=True)


def solvers():
    import scipy.sparse.linalg as spla
    from femreg.data_term import SSDTerm
    from femreg.image import SplineImage, normalize_pair
    from femreg.mesh import roi_mesh
    from femreg.pixels import PixelQuadrature
    from femreg.regularizers import make_regularizer
    from femreg.solver import SPDSolver
    ref, mov = make_pair()
    ref, mov, _ = normalize_pair(ref, mov)
    I1, I2 = SplineImage(ref, SPACING), SplineImage(mov, SPACING)
    for h in [1.0, 0.5]:
        mesh = roi_mesh(SHAPE, SPACING, element_size=h)
        data = SSDTerm(PixelQuadrature(mesh, SHAPE, SPACING, (0, 0)), I1, I2)
        reg = make_regularizer("strain")
        reg.setup(mesh)
        H = (data.hessian() + reg.hessian()).tocsc()
        b = np.random.default_rng(0).standard_normal(H.shape[0])
        print(f"\nh = {h} mm: {H.shape[0]} DOF, nnz {H.nnz}")
        x_, y_ = mesh.p
        B = np.zeros((H.shape[0], 3))
        B[0::2, 0] = 1.0
        B[1::2, 1] = 1.0
        B[0::2, 2], B[1::2, 2] = -y_, x_
        for method in ["splu", "spsolve", "amg-cg"]:
            s = SPDSolver(method, B=B if method == "amg-cg" else None)
            t = time.perf_counter()
            x = s.solve(H, b)
            t1 = time.perf_counter() - t
            t = time.perf_counter()
            s.solve(H, b, reuse=True)
            t2 = time.perf_counter() - t
            print(f"  {method:8s}: first solve {t1:.3f} s, repeat (reuse) {t2:.4f} s, "
                  f"rel. residual {np.linalg.norm(H @ x - b) / np.linalg.norm(b):.1e}")
        for spec in ["COLAMD", "NATURAL"]:
            t = time.perf_counter()
            spla.splu(H, permc_spec=spec)
            print(f"  splu permc_spec={spec}: {time.perf_counter() - t:.3f} s")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", action="store_true")
    ap.add_argument("--solvers", action="store_true")
    a = ap.parse_args()
    if a.solvers:
        solvers()
    elif a.study:
        study()
    else:
        timings()
