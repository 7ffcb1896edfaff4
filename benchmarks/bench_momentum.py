"""Benchmark: what the momentum regularisers (R_P_sigma, R_P_eps) cost.

1. Operator build (``momentum_jump_operators``, once per mesh) on the paper's 72 x 44 mm region for meshes from
   the engine's default (1 mm elements, ~3 k) up to ~50 k elements; time and tracemalloc peak; the per-call cost
   of energy + gradient and of the lagged-diffusivity Hessian (eq:dmreg2 to eq:dmreg4).
2. Per-Gauss-Newton-iteration cost of ``femreg.register`` on a paper-geometry speckle pair (3750 x 147 pixels,
   ~0.8 % axial compression, incompressible lateral expansion, a stiff-inclusion-like bump) with R_eps
   ("strain") and with the momentum terms, each at its default alpha; median over the iterations, best of
   ``--repeat`` runs (the machine is shared).
3. Where a momentum iteration's extra time goes: regulariser evaluation, Hessian, and the factorisation of
   H = H_data + H_R (which changes every iteration, unlike R_eps's, which the engine factorises once), with
   SciPy SuperLU (the engine's default) and, when installed, MKL PARDISO (SPD, analysis once).

Run:  python benchmarks/bench_momentum.py [--quick] [--repeat N]
"""
from __future__ import annotations

import argparse
import resource
import time
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skfem import MeshQuad1

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout, not an installed copy
import femreg  # noqa: E402
from femreg.regularizers import make_regularizer, momentum_jump_operators  # noqa: E402

PAPER_SPACING = (0.0192, 0.3)      # mm (axial 40 MHz at 1540 m/s, lateral 0.3 mm)
PAPER_SHAPE = (3750, 147)


def paper_field(points):
    """0.8 % axial compression, nu = 1/2 lateral expansion, plus a smooth 7.5 mm 'inclusion' bump at 30 mm."""
    p = np.asarray(points, float)
    x, y = p[:, 0], p[:, 1] - 22.0
    bump = np.exp(-((x - 30.0) ** 2 + y ** 2) / (2 * 4.0 ** 2))
    ux = -0.008 * x + 0.03 * bump
    uy = 0.004 * y - 0.01 * bump * y / 4.0
    return np.column_stack([ux, uy])


def timed(fn, repeat=3):
    best = np.inf
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def operator_build(sizes):
    print("\n== 1. operator build (once per mesh), 72 x 44 mm ROI ==")
    print(f"{'h mm':>6} {'elements':>9} {'edges':>8} {'K build s':>10} {'peak MB':>8} {'setup s':>8} "
          f"{'E+grad ms':>10} {'hess ms':>8}  variant")
    for h in sizes:
        mesh = MeshQuad1.init_tensor(np.arange(0, 72 + 1e-9, h), np.arange(0, 44 + 1e-9, h))
        for name in ("momentum-stress", "momentum-strain"):
            reg = make_regularizer(name)
            dil = reg.dilatation
            tracemalloc.start()
            tb, J = timed(lambda: momentum_jump_operators(mesh, reg.lambda_bar, dilatation=dil), repeat=1)
            peak = tracemalloc.get_traced_memory()[1] / 2**20
            tracemalloc.stop()
            ts, _ = timed(lambda: reg.setup(mesh), repeat=1)
            u = 1e-3 * np.random.default_rng(0).standard_normal(2 * mesh.p.shape[1])

            def eg():
                reg._cache = (None, None)       # force a fresh K u
                return reg.energy(u), reg.gradient(u)

            te, _ = timed(eg)
            th, _ = timed(lambda: reg.hessian(u))
            print(f"{h:6.2f} {mesh.t.shape[1]:9d} {J.n_edges:8d} {tb:10.3f} {peak:8.1f} {ts:8.3f} "
                  f"{1e3 * te:10.2f} {1e3 * th:8.2f}  {name}")


class _PardisoSPD:
    """Prototype of a proposed engine change (femreg.solver is not this module's): MKL PARDISO, real SPD,
    symbolic analysis once per sparsity pattern, numeric refactorisation when H changes."""

    def __init__(self):
        from pypardiso import PyPardisoSolver

        self._cls = PyPardisoSolver
        self._s = None
        self._pattern = None
        self._key = None

    def __call__(self, solver_self, H, b, reuse=False):
        if not (reuse and self._key is H):
            Hu = sp.triu(sp.csr_matrix(solver_self._shifted(H)), format="csr")
            Hu.sort_indices()
            pattern = (Hu.indptr.tobytes(), Hu.indices.tobytes())
            if self._s is None or pattern != self._pattern:
                self._s = self._cls(mtype=2)
                self._s.set_phase(11)
                self._s._call_pardiso(Hu, np.zeros(Hu.shape[0]))
                self._pattern = pattern
            self._s.set_phase(22)
            self._s._call_pardiso(Hu, np.zeros(Hu.shape[0]))
            self._Hu, self._key = Hu, H
            solver_self.n_factorizations += 1
        self._s.set_phase(33)
        return self._s._call_pardiso(self._Hu, np.asarray(b, float))


def per_iteration(repeat, quick):
    shape = (1875, 147) if quick else PAPER_SHAPE
    print(f"\n== 2. Gauss-Newton iteration cost, speckle pair {shape[0]} x {shape[1]} px, engine's default mesh ==")
    from femreg import solver as engine_solver
    from femreg.synthetic import speckle_pair

    ref, mov = speckle_pair(paper_field, shape=shape, spacing=PAPER_SPACING, seed=0, snr_db=20)
    alphas = {"strain": 3.0, "momentum-stress": None, "momentum-strain": None}   # R_eps: its best in the sweeps
    solvers = {"engine SuperLU": None}
    try:
        import pypardiso  # noqa: F401
        solvers["PARDISO (proposed)"] = _PardisoSPD
    except ImportError:
        print("(pypardiso not installed: PARDISO rows skipped)")
    original = engine_solver.SPDSolver.solve
    for label, factory in solvers.items():
        rows = {}
        for name, alpha in alphas.items():
            best = None
            for _ in range(repeat):
                if factory is not None:
                    impl = factory()
                    engine_solver.SPDSolver.solve = lambda self, H, b, reuse=False, _i=impl: _i(self, H, b, reuse)
                try:
                    res = femreg.register(ref, mov, spacing=PAPER_SPACING, regularizer=name, alpha=alpha)
                finally:
                    engine_solver.SPDSolver.solve = original
                it = np.asarray(res.timings["per_iteration"], float)
                med = float(np.median(it[1:])) if it.size > 1 else float(it[0])
                if best is None or med < best[0]:
                    best = (med, res)
            med, res = best
            rows[name] = med
            true = paper_field(res.mesh.p.T)
            err = np.linalg.norm(res.u[1::2] - true[:, 1]) / np.linalg.norm(true[:, 1])
            print(f"[{label}] {name:16s} alpha={res.alpha:<5g} nit={res.nit:2d}  median s/iter (after the first) "
                  f"{med:.3f}  first {res.timings['per_iteration'][0]:.3f}  total {res.timings['total']:.2f} s  "
                  f"lateral err {100 * err:.1f} %  n_dof={res.u.size}")
        for name in ("momentum-stress", "momentum-strain"):
            print(f"[{label}] overhead of {name} vs strain per iteration: "
                  f"{100 * (rows[name] / rows['strain'] - 1):+.0f} %")
    return ref, mov


def breakdown(ref, mov):
    print("\n== 3. where the momentum iteration's extra time goes (engine's mesh and data Hessian) ==")
    from femreg.data_term import SSDTerm
    from femreg.image import SplineImage, normalize_pair
    from femreg.mesh import roi_mesh
    from femreg.pixels import PixelQuadrature

    r, m, _ = normalize_pair(ref, mov)
    I1, I2 = SplineImage(r, PAPER_SPACING), SplineImage(m, PAPER_SPACING)
    mesh = roi_mesh(r.shape, PAPER_SPACING, (0.0, 0.0))
    data = SSDTerm(PixelQuadrature(mesh, r.shape, PAPER_SPACING, (0.0, 0.0)), I1, I2)
    nodes = mesh.p.T
    u = np.empty(2 * len(nodes))
    u[0::2], u[1::2] = paper_field(nodes).T
    td, _ = timed(lambda: (data.energy(u), data.gradient(u)))
    print(f"data term energy + gradient: {1e3 * td:.1f} ms   (n_dof = {u.size})")
    Hd = data.hessian(u)
    for name in ("strain", "momentum-stress", "momentum-strain"):
        reg = make_regularizer(name, alpha=3.0 if name == "strain" else None)    # as in section 2
        reg.setup(mesh)
        te, _ = timed(lambda: (reg.energy(u), reg.gradient(u)))
        th, Hr = timed(lambda: reg.hessian(u))
        H = sp.csc_matrix(Hd + Hr)
        tf, _ = timed(lambda: spla.splu(H, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}),
                      repeat=2)
        # SPD: no pivoting needed; SuperLU's default threshold pivoting can multiply the fill (see the numbers)
        tf0, _ = timed(lambda: spla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                         options={"SymmetricMode": True}), repeat=2)
        line = (f"{name:16s} R energy+grad {1e3 * te:6.2f} ms  R hessian {1e3 * th:6.2f} ms  "
                f"nnz(H) {H.nnz:7d}  SuperLU factor {1e3 * tf:7.1f} ms (no pivoting {1e3 * tf0:6.1f} ms)")
        try:
            from pypardiso import PyPardisoSolver

            Hu = sp.triu(sp.csr_matrix(H), format="csr")
            Hu.sort_indices()
            s = PyPardisoSolver(mtype=2)         # real SPD
            s.set_phase(11)
            s._call_pardiso(Hu, np.zeros(H.shape[0]))

            def refactor():
                s.set_phase(22)
                s._call_pardiso(Hu, np.zeros(H.shape[0]))

            tp, _ = timed(refactor, repeat=2)
            line += f"  PARDISO SPD refactor {1e3 * tp:6.1f} ms"
        except ImportError:
            line += "  (pypardiso not installed)"
        print(line)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller meshes and half-height image")
    ap.add_argument("--repeat", type=int, default=2, help="registrations per regulariser (best is kept)")
    args = ap.parse_args(argv)
    sizes = (1.0, 0.5) if args.quick else (1.0, 0.5, 0.3, 0.25, 0.2)
    operator_build(sizes)
    ref, mov = per_iteration(max(1, args.repeat), args.quick)
    breakdown(ref, mov)
    print(f"\npeak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
