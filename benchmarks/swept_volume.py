"""Swept-probe volumes against Cartesian volumes of the same field: total strain error over the interior.

A swept pair (``forward.swept.make_swept_pair``: a linear or convex array rocked in elevation, rendered along its
fan frames) is registered with ``femreg.register(..., geometry=femreg.Swept(...))`` (scan-converted inside the fan,
:mod:`femreg.swept`); the Cartesian pair (``forward.volume.make_volume_pair``: the same probe's PSF on its
Cartesian voxel grid, the same field) covers the swept pair's registered box.  Both are scored on the same points:
a lattice over the swept result's mesh box less ``--margin`` mm, total strain error = relative L2 of the six
strain components with the shears counted twice.  Fields: an affine compression (1 %) with shears (xy 0.3 %,
xz 0.5 %), and the paper's 3D stiff sphere (15 mm, 4x stiffer, at 30 mm depth; the cached 3D FE solution scaled
to 1 % mean axial strain over the box).  Two seeds each.  The alternative to scan conversion is measured too: from
the scan-converted result, Gauss-Newton of eq:objf on the same mesh with the native samples as the image term's
quadrature points (their physical positions, weights |det J| dr dl dphi, the warp through the inverse mapping,
grad I_1 = J^-T times the knot gradient in the sample indices: the 2D beam quadrature of femreg.geometry in 3D).

    python benchmarks/swept_volume.py [--cases affine sphere] [--seeds 0 1] [--json rows.json]
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WEIGHTS = np.array([1, 1, 1, 2, 2, 2.0])


# -- the alternative: the image term on the native samples ----------------------------------------------------
class SweptSampleTerm:
    """SSD image term (eq:IR, fixed reference gradient eq:wfnew) with the native samples of a swept pair as the
    quadrature points, on an axis-aligned tensor hexahedral mesh in physical space: each sample at its physical
    position with the weight of the physical volume it represents, ``|det J| dr dl dphi`` mm^3; the warp
    I_2(x + u) evaluates the moving volume's tricubic spline at the sample indices of x + u (the geometry's
    inverse mapping); grad_x I_1 = J^{-T} (the knot gradient in the sample indices), J = d(x, y, z)/d(i, j, k).
    The interface :class:`femreg.solver.Objective` uses (energy, gradient, hessian)."""

    hessian_fixed = True

    def __init__(self, mesh, geometry, ref, mov, spacing, origin):
        from femreg.voxels import SplineVolume, tensor_axes_3d

        ax, node = tensor_axes_3d(mesh)
        self.geometry, self.shape = geometry, ref.shape
        self.spacing, self.origin = np.asarray(spacing, float), np.asarray(origin, float)
        I1 = SplineVolume(ref, (1.0, 1.0, 1.0))
        self.moving = SplineVolume(mov, (1.0, 1.0, 1.0), keep_data=False)
        X = np.column_stack([c.ravel() for c in geometry.sample_positions(ref.shape, spacing, origin)])
        lo = np.array([a[0] for a in ax])
        hi = np.array([a[-1] for a in ax])
        keep = np.flatnonzero(np.all((X >= lo) & (X <= hi), axis=1))
        self.index = keep
        self.points = X[keep]
        del X
        # trilinear basis of the tensor mesh at the samples
        cols, vals = [], []
        cell, t = [], []
        for a in range(3):
            c = np.clip(np.searchsorted(ax[a], self.points[:, a], side="right") - 1, 0, ax[a].size - 2)
            cell.append(c)
            t.append((self.points[:, a] - ax[a][c]) / (ax[a][c + 1] - ax[a][c]))
        for i in (0, 1):
            for j in (0, 1):
                for k in (0, 1):
                    cols.append(node[cell[0] + i, cell[1] + j, cell[2] + k])
                    vals.append((t[0] if i else 1 - t[0]) * (t[1] if j else 1 - t[1]) * (t[2] if k else 1 - t[2]))
        n = len(keep)
        import scipy.sparse as sp
        self.P = sp.csr_matrix((np.stack(vals, 1).ravel(), np.stack(cols, 1).ravel(),
                                np.arange(0, 8 * n + 1, 8)), shape=(n, mesh.p.shape[1]))
        # the reference: values and physical gradient at the samples; weights
        ii = np.unravel_index(keep, ref.shape)
        g_idx = I1.gradient_at_voxels(tuple(slice(0, s) for s in ref.shape))
        g_idx = np.column_stack([g[ii] for g in g_idx])                       # dI/d(i, j, k)
        self.ref_values = np.asarray(ref, float)[ii]
        del I1
        r = origin[0] + ii[0] * spacing[0]
        line = geometry._line(ii[1], ref.shape, spacing, origin)
        phi = geometry.frame_angles(ref.shape[2])[ii[2]]
        J = geometry.jacobian(r, line, phi)
        dl = spacing[1] if geometry.array is None else geometry.array.pitch_rad
        J = J * np.array([spacing[0], dl, geometry.step_rad])[None, None, :]   # d(x, y, z)/d(i, j, k)
        self.g = np.linalg.solve(np.swapaxes(J, 1, 2), g_idx[:, :, None])[:, :, 0]   # J^{-T} grad_idx
        self.w0 = np.abs(np.linalg.det(J))
        self.w = self.w0.copy()
        self._H = None
        self._cache = (None, None)

    def _idx(self, u):
        U = np.column_stack([self.P @ u[a::3] for a in range(3)])
        return self.geometry.physical_to_index(self.points + U, self.shape, self.spacing, self.origin)

    def warped_moving(self, u) -> np.ndarray:
        return self.moving.at_index(self._idx(np.asarray(u, float)))

    def outside_mask(self, u) -> np.ndarray:
        idx = self._idx(np.asarray(u, float))
        hi = np.asarray(self.shape, float)[:, None] - 2.0
        return np.any((idx < 1.0) | (idx > hi), axis=0)

    def residual(self, u) -> np.ndarray:
        key, val = self._cache
        if key is not None and np.array_equal(key, u):
            return val
        r = self.warped_moving(u) - self.ref_values
        self._cache = (np.array(u, copy=True), r)
        return r

    def energy(self, u) -> float:
        r = self.residual(u)
        return 0.5 * float(np.sum(self.w * r * r))

    def gradient(self, u) -> np.ndarray:
        wr = self.w * self.residual(u)
        out = np.empty(3 * self.P.shape[1])
        for a in range(3):
            out[a::3] = self.P.T @ (wr * self.g[:, a])
        return out

    def hessian(self, u=None):
        if self._H is None:
            import scipy.sparse as sp

            n = self.P.shape[1]
            P = self.P.tocoo()
            blocks = []
            for a in range(3):      # G_a = diag(g_a) P, its columns at the node's a-th DOF
                blocks.append(sp.csr_matrix((P.data * self.g[P.row, a], (P.row, 3 * P.col + a)),
                                            shape=(P.shape[0], 3 * n)))
            G = blocks[0] + blocks[1] + blocks[2]
            self._H = (G.T @ sp.diags(self.w) @ G).tocsr()
        return self._H

    def ncc(self, u) -> float:
        b = self.warped_moving(u)
        return float(np.corrcoef(self.ref_values, b)[0, 1])


def solve_on_samples(res, geometry, ref, mov, spacing, origin, *, maxiter=20, tol=1e-3,
                     regularizer_options=None):
    """Gauss-Newton of eq:objf on ``res``'s mesh with the native samples as the image term's quadrature
    (:class:`SweptSampleTerm`), from ``res.u``; returns ``(u, gn, term)``."""
    from femreg.linsolve import SPDSolver
    from femreg.scaling import effective_alpha
    from femreg.solver import GN_STRAIN_TOL, Objective, gauss_newton
    from femreg.strategy import component_tol, effective_regularizer_options, fresh_regularizer
    from femreg.volume_fields import element_strain_operator_3d

    ref = ref / np.sqrt(np.mean(ref ** 2))
    mov = mov / np.sqrt(np.mean(mov ** 2))
    term = SweptSampleTerm(res.mesh, geometry, ref, mov, spacing, origin)
    out = term.outside_mask(res.u)
    if out.any() and not out.all():
        term.w = np.where(out, 0.0, term.w0)
    reg = fresh_regularizer(res.regularizer, res.alpha,
                            effective_regularizer_options("auto", res.regularizer, regularizer_options))
    reg.alpha = effective_alpha(reg.alpha, res.mesh)
    reg.setup(res.mesh)
    gn = gauss_newton(Objective(term, reg), res.u, maxiter=maxiter,
                      tol=component_tol(tol, res.u.reshape(-1, 3)[:, :2].ravel()),
                      linear_solver=SPDSolver("auto", large_method="pardiso"), strain_tol=GN_STRAIN_TOL,
                      strain_operator=element_strain_operator_3d(res.mesh))
    return gn.x, gn, term



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
    "affine-large": (dict(sweep_radius_mm=20.0, angle_step_deg=1.0), "matrix7", 20.0, 3.0, 100, 41),
    "affine-large-0.5deg": (dict(sweep_radius_mm=20.0, angle_step_deg=0.5), "matrix7", 20.0, 3.0, 100, 81),
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
    t = time.process_time()
    u, gn, _ = solve_on_samples(rs, geo, np.asarray(p.ref, float), np.asarray(p.mov, float), np.array(p.spacing),
                                np.array(p.origin))
    tn = time.process_time() - t
    rn = copy.copy(rs)
    rn.u, rn._nodal_strain, rn._grids = u, None, {}
    m = ARGS.margin
    en = total_strain_error(rn, field, lo + m, hi - m)[0]
    es, fs = total_strain_error(rs, field, lo + m, hi - m)
    ec, fc = total_strain_error(rc, field, lo + m, hi - m)
    row = dict(case=case, seed=seed, samples_error=en, samples_cpu_s=tn, samples_nit=gn.nit, swept_error=es,
               swept_cover=fs, swept_cpu_s=ts, swept_success=rs.success,
               cartesian_error=ec, cartesian_cover=fc, cartesian_cpu_s=tc, cartesian_success=rc.success,
               swept_shape=list(p.ref.shape), scan_converted=list(rs.cartesian[0]),
               grid_spacing=[float(v) for v in rs.cartesian[1]], cartesian_shape=list(c.ref.shape),
               box=[float(v) for v in np.ravel([lo, hi])], excluded=rs.excluded)
    print(f"| {case} | {seed} | {es:.2f} % ({ts:.0f} s{'' if rs.success else ', FAILED'}) | {en:.2f} % (+{tn:.0f} s) | "
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
    print("| case | seed | swept, scan-converted (CPU) | swept, then on the samples (+CPU) | Cartesian (CPU) | "
          "samples -> voxels @ spacing |\n|---|---|---|---|---|---|")
    rows = [run(c, s, ARGS.grid) for c in ARGS.cases for s in ARGS.seeds]
    if ARGS.json:
        Path(ARGS.json).write_text(json.dumps(rows, indent=1))


ARGS = None

if __name__ == "__main__":
    main()
