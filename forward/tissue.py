"""Heterogeneous tissue: a block whose Young's modulus varies smoothly and randomly, compressed from the top.

Real tissue is neither a uniform block nor one disk in a background: its stiffness varies everywhere, on the
scale of a few millimetres, by a factor of a few.  :class:`RandomTissue` is that case with a known truth: the
modulus ``E(x) = exp(sigma g(x))`` (relative units, median about 1) with ``g`` a Gaussian random field of unit
variance and correlation length ``corr_mm`` (white noise smoothed by a Gaussian kernel of standard deviation
``corr_mm``), the small-strain equilibrium ``div sigma = 0`` (eq:meq's physics; plane strain or plane stress,
Poisson's ratio 0.495) solved with scikit-fem on a tensor mesh of biquadratic quads (Q2: nearly incompressible
plane strain does not lock), a frictionless compression: the top face (the probe) pushed down by
``level x depth``, the bottom face held axially, the sides free.  Seeded: the same arguments give the same field.

Fields are returned in the probe's frame (the top face at rest, its centre at rest laterally), as
:class:`forward.fields.Inclusion`: the mean axial strain is ``-level``.  Displacement and strain are sampled from
the FE solution on a 0.1 mm grid and interpolated bilinearly (the strain is the FE solution's own gradient at the grid points): adequate for images of 0.02-0.5 mm pixels and elements of 0.3 mm and more.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["RandomTissue"]


class RandomTissue:
    """A compressed block of smoothly heterogeneous tissue (FE ground truth; module docstring).

    Parameters
    ----------
    seed : int
        Seeds the modulus field.
    level : float
        Mean axial compression (fraction, 0.001-0.1).
    model : {"plane-stress", "plane-strain"}
    sigma : float
        Standard deviation of ``log E`` (0.5: E within x/ 2.7 of its median for 95 % of the tissue).
    corr_mm : float
        Correlation length of ``log E``, mm.
    size_mm : (depth, width)
        The block, mm: depth from the probe face (x 0 .. depth), width centred on y = 0.
    h_mm : float
        FE element size (Q2), mm.
    """

    GRID_MM = 0.1

    def __init__(self, seed: int = 0, level: float = 0.01, model: str = "plane-stress", *, sigma: float = 0.5,
                 corr_mm: float = 2.0, size_mm=(56.0, 56.0), h_mm: float = 0.5, poisson: float = 0.495):
        if model not in ("plane-stress", "plane-strain"):
            raise ValueError(f"model must be 'plane-strain' or 'plane-stress', got {model!r}")
        level = float(level)
        if not (math.isfinite(level) and 0 < abs(level) <= 0.2):
            raise ValueError(f"level must be a compression fraction in (0, 0.2], got {level!r}")
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"sigma must be >= 0, got {sigma!r}")
        if not (math.isfinite(corr_mm) and corr_mm > 0):
            raise ValueError(f"corr_mm must be > 0, got {corr_mm!r}")
        depth, width = (float(s) for s in size_mm)
        if not (depth > 4 * corr_mm and width > 4 * corr_mm):
            raise ValueError(f"size_mm {size_mm!r} too small for corr_mm {corr_mm:g}")
        self.seed, self.level, self.model = int(seed), level, model
        self.sigma, self.corr_mm, self.size_mm = float(sigma), float(corr_mm), (depth, width)
        self.name = f"random tissue seed {seed} sigma {sigma:g} corr {corr_mm:g} mm {model} {100 * level:g}%"
        self._solve(h_mm, poisson)

    # ------------------------------------------------------------------------------------------------------
    def _grid_axes(self):
        """(xs, ys) mm of the modulus grid: depth 0 .. depth, width centred on 0, every :attr:`GRID_MM`."""
        g_h = self.GRID_MM
        depth, width = self.size_mm
        return np.arange(0.0, depth + 0.5 * g_h, g_h), np.arange(-width / 2, width / 2 + 0.5 * g_h, g_h)

    def _log_modulus_grid(self):
        from scipy.ndimage import gaussian_filter

        g_h = self.GRID_MM
        xs, ys = self._grid_axes()
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 20261205]))
        # periodic smoothing would tie the block's faces together; 'reflect' keeps the field stationary enough
        g = gaussian_filter(rng.standard_normal((len(xs), len(ys))), self.corr_mm / g_h, mode="reflect")
        g = (g - g.mean()) / (g.std() if g.std() > 0 else 1.0)
        return xs, ys, self.sigma * g

    def _solve(self, h_mm, poisson):
        from scipy.interpolate import RegularGridInterpolator
        from skfem import (Basis, BilinearForm, ElementQuad2, ElementVector, MeshQuad, asm, condense, solve)
        from skfem.helpers import ddot, sym_grad, trace

        xs, ys, logE = self._log_modulus_grid()
        self._logE = RegularGridInterpolator((xs, ys), logE, bounds_error=False, fill_value=None)
        depth, width = self.size_mm
        nx, ny = int(round(depth / h_mm)), int(round(width / h_mm))
        mesh = MeshQuad.init_tensor(np.linspace(0, depth, nx + 1), np.linspace(-width / 2, width / 2, ny + 1))
        basis = Basis(mesh, ElementVector(ElementQuad2()))
        nu = float(poisson)
        # Lame parameters per unit E: plane strain lambda, plane stress lambda* = 2 lambda mu / (lambda + 2 mu)
        lam = nu / ((1 + nu) * (1 - 2 * nu)) if self.model == "plane-strain" else nu / ((1 + nu) * (1 - nu))
        mu = 1.0 / (2 * (1 + nu))
        xq = np.asarray(basis.global_coordinates().value)
        E_q = np.exp(self._logE(np.stack([xq[0].ravel(), xq[1].ravel()], axis=1))).reshape(xq[0].shape)

        @BilinearForm
        def stiffness(u, v, w):
            eu, ev = sym_grad(u), sym_grad(v)
            return w["E"] * (lam * trace(eu) * trace(ev) + 2 * mu * ddot(eu, ev))

        K = asm(stiffness, basis, E=E_q)
        top = basis.get_dofs(lambda p: np.isclose(p[0], 0.0))
        bottom = basis.get_dofs(lambda p: np.isclose(p[0], depth))
        u = np.zeros(basis.N)
        ux_top = top.nodal["u^1"]
        u[ux_top] = self.level * depth
        if "u^1" in top.facet:
            u[top.facet["u^1"]] = self.level * depth
        fixed = [ux_top, bottom.nodal["u^1"]] + [d["u^1"] for d in (top.facet, bottom.facet) if "u^1" in d]
        # one lateral DOF at the bottom centre removes the rigid lateral motion
        bn = bottom.nodal["u^2"]
        centre = bn[np.argmin(np.abs(basis.doflocs[1, bn]))]
        fixed.append(np.array([centre]))
        u = solve(*condense(K, np.zeros(basis.N), x=u, D=np.concatenate(fixed)))

        # the FE solution and its own gradient on the 0.1 mm grid: the grid points are reference points of the
        # tensor mesh's elements (a quadrature rule of them), so no point search is needed
        k = max(1, int(round(depth / nx / self.GRID_MM)))
        r = np.linspace(0.0, 1.0, k + 1)
        R = np.array(np.meshgrid(r, r, indexing="ij")).reshape(2, -1)
        pb = Basis(mesh, ElementVector(ElementQuad2()), quadrature=(R, np.full(R.shape[1], 1.0 / R.shape[1])))
        f = pb.interpolate(u)
        xq = np.asarray(pb.global_coordinates().value)          # (2, n_el, n_pts)
        gx = np.linspace(0.0, depth, nx * k + 1)
        gy = np.linspace(-width / 2, width / 2, ny * k + 1)
        ii = np.rint(xq[0] / (depth / (nx * k))).astype(int).ravel()
        jj = np.rint((xq[1] + width / 2) / (width / (ny * k))).astype(int).ravel()
        val, grad = np.asarray(f.value), np.asarray(f.grad)      # (2, n_el, n_pts), (2, 2, n_el, n_pts)
        U = np.zeros((2, len(gx), len(gy)))
        G = np.zeros((2, 2, len(gx), len(gy)))
        U[:, ii, jj] = val.reshape(2, -1)
        G[:, :, ii, jj] = grad.reshape(2, 2, -1)
        # the probe's frame: the top face at rest, its centre at rest laterally
        j0 = int(np.argmin(np.abs(gy)))
        U[0] -= self.level * depth
        U[1] -= U[1, 0, j0]
        exx, eyy, exy = G[0, 0], G[1, 1], 0.5 * (G[0, 1] + G[1, 0])
        stack = np.stack([U[0], U[1], exx, eyy, exy], axis=-1)
        self._interp = RegularGridInterpolator((gx, gy), stack, bounds_error=False, fill_value=np.nan)

    # ------------------------------------------------------------------------------------------------------
    def _at(self, points) -> np.ndarray:
        p = np.atleast_2d(np.asarray(points, float))
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError(f"points must be (n, 2) [x, y] mm, got shape {np.shape(points)}")
        return self._interp(p)

    def displacement(self, points) -> np.ndarray:
        """(n, 2) [ux, uy] mm at ``points`` (n, 2) mm; NaN outside the block."""
        return self._at(points)[:, :2]

    def strain(self, points) -> np.ndarray:
        """(n, 3) [exx, eyy, exy] at ``points`` (n, 2) mm; NaN outside the block."""
        return self._at(points)[:, 2:]

    def modulus(self, points) -> np.ndarray:
        """(n,) relative Young's (and shear) modulus ``exp(sigma g)`` at ``points`` (n, 2) mm."""
        p = np.atleast_2d(np.asarray(points, float))
        return np.exp(self._logE(p))

    def __repr__(self) -> str:
        return f"RandomTissue({self.name})"


class LayeredTissue(RandomTissue):
    """Horizontal layers (parallel to the probe face) in series under compression, FE ground truth as
    :class:`RandomTissue` (free lateral sides, the top face pressed by ``level``, the bottom held axially).

    Parameters
    ----------
    interfaces_mm : sequence of float
        Depths of the interfaces between layers, mm, increasing.
    moduli : sequence of float
        Relative Young's (and shear) modulus of each layer from the top, ``len(interfaces_mm) + 1`` values.
    level, model, size_mm, h_mm, poisson
        As :class:`RandomTissue`.
    """

    def __init__(self, interfaces_mm=(10.0,), moduli=(2.0, 1.0), level: float = 0.01, model: str = "plane-strain",
                 *, size_mm=(20.0, 20.0), h_mm: float = 0.5, poisson: float = 0.495):
        z = [float(v) for v in interfaces_mm]
        m = [float(v) for v in moduli]
        if len(m) != len(z) + 1 or any(v <= 0 or not math.isfinite(v) for v in m):
            raise ValueError(f"moduli must be {len(z) + 1} positive numbers, got {moduli!r}")
        if any(b <= a for a, b in zip(z, z[1:])) or not all(0 < v < float(size_mm[0]) for v in z):
            raise ValueError(f"interfaces_mm must increase inside the depth {size_mm[0]!r}, got {interfaces_mm!r}")
        if model not in ("plane-stress", "plane-strain"):
            raise ValueError(f"model must be 'plane-strain' or 'plane-stress', got {model!r}")
        self.interfaces, self.moduli = tuple(z), tuple(m)
        self.seed, self.level, self.model = 0, float(level), model
        self.sigma, self.corr_mm, self.size_mm = 0.0, 1.0, tuple(float(v) for v in size_mm)
        self.name = (f"layers {'/'.join(f'{v:g}' for v in m)} at {', '.join(f'{v:g}' for v in z)} mm {model} "
                     f"{100 * self.level:g}%")
        self._solve(h_mm, poisson)

    def _log_modulus_grid(self):
        xs, ys = self._grid_axes()
        layer = np.searchsorted(np.asarray(self.interfaces), xs)
        logE = np.log(np.asarray(self.moduli))[layer]
        return xs, ys, np.repeat(logE[:, None], len(ys), axis=1)

    def __repr__(self) -> str:
        return f"LayeredTissue({self.name})"

