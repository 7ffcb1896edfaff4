"""Benchmark of ``femreg.register`` on a paper-geometry pair (3750 x 147 pixels, dx 0.0192 mm, dy 0.3 mm).

The pair is synthetic (femreg.synthetic: PSF-convolved speckle, SNR 12 dB, warped by a known smooth field with
0.4-0.8 % axial compression).  For every registered regulariser it prints the
time of each stage (block matching, operator build, regulariser set-up, each Gauss-Newton iteration, total) and
the peak memory (each regulariser runs in a fresh process so that ru_maxrss is its own).

    python benchmarks/bench_register.py                 # timings (paper-size pair, then 1200 x 125 pairs)
    python benchmarks/bench_register.py --save a.npz    # ... and keep every nodal u; --compare a.npz: max |du|
    python benchmarks/bench_register.py --no-compiled   # without the numba loops (femreg._kernels)
    python benchmarks/bench_register.py --study         # alpha and element-size study (total strain error)
    python benchmarks/bench_register.py --solvers       # linear-solver comparison on the GN system

Measured 2026-11-29 on the shared 2-core machine under a load average of 10-12 (so pessimistic; fastest of 5),
default 2 mm mesh (792 nodes), numba installed: total 0.39-0.52 s per pair (R_P_sigma 0.39 s), 0.72 s for R_P_eps
(its block matching took longer); a Gauss-Newton iteration after the first 18-30 ms (was 107-151 ms in the same
conditions before the compiled image-term loops and the banded Cholesky: total 1.4-1.75 s); operator build
24-68 ms (was 190-230 ms); block matching 0.16-0.26 s is now the largest stage.  1200 x 125 pairs: 0.26 s at
0.5 % strain (was 0.48 s), 0.9-1.1 s at 2-5 % (was 1.3-1.8 s; block matching and the coarse pass dominate).  Peak
RSS ~400 MB (140 MB of it the Python process, imports and the pair).  Results equal to the earlier code's to
2e-13 mm (``--save`` / ``--compare``).
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


def uniform_field(strain):
    """Uniform axial compression ``strain`` with half as much lateral expansion, about the image centre."""
    def f(p):
        x, y = p[:, 0], p[:, 1]
        return np.column_stack([-strain * (x - 0.5 * SMALL[0] * SPACING[0]),
                                0.5 * strain * (y - 0.5 * SMALL[1] * SPACING[1])])
    return f


#: The small pair of the speed targets (23 x 37.5 mm at the paper's sampling).
SMALL = (1200, 125)


def _run_one(name, alpha, element_size, q, repeat=1, strain=None):
    import femreg
    from femreg.metrics import field_errors
    from femreg.synthetic import speckle_pair
    field = paper_field if strain is None else uniform_field(strain)
    ref, mov = make_pair() if strain is None else speckle_pair(field, SMALL, SPACING, seed=1, snr_db=20.0)
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
    err = field_errors(res, field)
    q.put(dict(name=name, u=res.u, alpha=res.alpha, timings=res.timings, total=total, nit=res.nit, success=res.success,
               message=res.message, err=err, n_nodes=res.mesh.p.shape[1], ncc=(res.ncc_before, res.ncc_after),
               rss_before_mb=base / 1024, peak_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def run_isolated(name, alpha=None, element_size=None, repeat=1, strain=None):
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_run_one, args=(name, alpha, element_size, q, repeat, strain))
    p.start()
    out = q.get()
    p.join()
    return out


def timings(save=None, compare=None):
    from femreg.regularizers import available_regularizers
    us = {}
    print(f"paper-geometry pair {SHAPE}, spacing {SPACING} mm, SNR 12 dB; fastest of 5 runs per regulariser")
    for name in available_regularizers():
        r = run_isolated(name, repeat=5)
        us[name] = r["u"]
        t = r["timings"]
        it = t["per_iteration"]
        print(f"\n[{name}] alpha={r['alpha']:g}  nodes={r['n_nodes']}  nit={r['nit']}  success={r['success']}  "
              f"({r['message']})")
        print("  " + " | ".join(f"{k} {v:.3f} s" for k, v in t.items()
                                 if isinstance(v, float) and k not in ("total", "gauss_newton")))
        if it:
            print(f"  GN: first iteration {it[0]:.3f} s (incl. Hessian assembly + factorisation), "
                  f"later {np.mean(it[1:]) if len(it) > 1 else float('nan'):.3f} s/iter, "
                  f"GN total {t['gauss_newton']:.3f} s")
        print(f"  TOTAL {r['total']:.3f} s   peak RSS {r['peak_mb']:.0f} MB "
              f"(after imports+pair {r['rss_before_mb']:.0f} MB)")
        e = r["err"]
        print(f"  errors: ux {100*e['ux']:.2f} %  uy {100*e['uy']:.1f} %  exx {100*e['exx']:.1f} %  "
              f"eyy {100*e['eyy']:.1f} %  exy {100*e['exy']:.1f} %  total strain {100*e['e']:.1f} %   "
              f"NCC {r['ncc'][0]:.3f} -> {r['ncc'][1]:.3f}")
    print(f"\n{SMALL[0]} x {SMALL[1]} pairs, uniform compression, SNR 20 dB, default register (R_P_sigma); "
          "fastest of 3")
    for strain in (0.005, 0.02, 0.05):
        r = run_isolated("momentum-stress", repeat=3, strain=strain)
        us[f"small-{strain}"] = r["u"]
        t, e = r["timings"], r["err"]
        print(f"  strain {100 * strain:3.1f} %: TOTAL {r['total']:.3f} s (initial guess {t.get('initial', 0.0):.3f} s, "
              f"{r['nit']} GN iterations {t.get('gauss_newton', 0.0):.3f} s)  total strain error {100 * e['e']:.1f} %  "
              f"ux {100 * e['ux']:.2f} %  success={r['success']}")
    if save:
        np.savez(save, **us)
    if compare:
        with np.load(compare) as z:
            print("\nmax |u - u_saved| (mm): " + ", ".join(f"{k} {np.abs(v - z[k]).max():.1e}" for k, v in us.items()
                                                       if k in z))


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
        for method in ["cholesky", "splu", "spsolve", "amg-cg"]:
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
    ap.add_argument("--save", help="write every registration's nodal u to this .npz")
    ap.add_argument("--compare", help="print max |u - u_saved| against a --save file")
    ap.add_argument("--no-compiled", action="store_true", help="use the scipy/numpy paths instead of numba's")
    a = ap.parse_args()
    if a.no_compiled:
        from femreg import _kernels
        _kernels.HAVE_NUMBA = False       # before the forks of run_isolated: they inherit it
    if a.solvers:
        solvers()
    elif a.study:
        study()
    else:
        timings(a.save, a.compare)
