r"""Linear elastic forward models of the paper's phantom (ground truth), solved with scikit-fem.

Strong form (small strain, quasi-static, no body force), per region :math:`\Omega_r` with Young's modulus
:math:`E_r` and Poisson ratio :math:`\nu`:

.. math::
    -\nabla\cdot\sigma(u) = 0,\quad \sigma = 2\mu\,\varepsilon(u) + \lambda\,\mathrm{tr}\,\varepsilon(u)\,I,\quad
    \varepsilon(u) = \tfrac12(\nabla u + \nabla u^T),

with :math:`\mu = E/(2(1+\nu))`, :math:`\lambda = E\nu/((1+\nu)(1-2\nu))` (plane strain, 3D) or
:math:`\lambda^* = E\nu/(1-\nu^2)` (plane stress).  Boundary conditions: bottom face ``u = 0``; compression patch
``u_x = compression_mm`` (slip: the tangential components are free, no tangential traction); all other faces
traction-free; on symmetry planes the normal component is zero.  Weak form: find ``u`` with
:math:`\int 2\mu\,\varepsilon(u):\varepsilon(v) + \lambda\,\mathrm{div}\,u\,\mathrm{div}\,v = 0` for all admissible
``v``.

Discretisation: P2 Lagrange elements on straight-sided triangles (2D) / tetrahedra (3D).  P2 is used because at
:math:`\nu = 0.495` (:math:`\lambda/\mu \approx 99`) P1 triangles/tets lock; P2 is free of visible locking at that
ratio and gives strains that are continuous inside each element, which point evaluation of the ground truth needs.
Triangles rather than quads in 2D: the map of a straight triangle is affine, so point evaluation inverts it in
closed form (no Newton iteration) and strains are exact FE values, and gmsh meshes the disk without recombination.
The 3D model is by default a quarter model (two symmetry planes through the inclusion centre), solved with MKL
PARDISO (``pypardiso``, from PyPI): about 240 k DOFs at the default 1 mm / 16 mm mesh.

Point evaluation (:meth:`Solution.displacement`, :meth:`Solution.strain`): a KD-tree on element centroids gives a
few candidate elements per point, a vectorised affine inverse gives barycentric coordinates, and the P2 shape
functions are evaluated there -- exact FE values.  Points outside the domain give NaN
(or ``ValueError`` with ``outside="raise"``).

Public names: :func:`solve_elasticity`, :class:`Solution`, :func:`load_solution`, :func:`cached_solve`,
:func:`lame_parameters`, :func:`elasticity_form`.
"""
from __future__ import annotations

import hashlib
import json
import os
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from femreg.io import atomic_savez

__all__ = ["solve_elasticity", "Solution", "load_solution", "cached_solve", "lame_parameters",
           "elasticity_form", "cache_dir", "MODELS"]

MODELS = ("plane-strain", "plane-stress", "3d")
#: bump when a change alters solutions, so stale cache entries are not reused
CACHE_VERSION = 1

#: Default element sizes (mm) in the refined region / far away, per model.
DEFAULT_MESH = {"plane-strain": (0.5, 8.0), "plane-stress": (0.5, 8.0), "3d": (1.0, 16.0)}


# ----------------------------------------------------------------------------------------------------------------
# physics
# ----------------------------------------------------------------------------------------------------------------
def lame_parameters(E, nu, model: str = "plane-strain"):
    """Lamé parameters ``(lam, mu)`` (MPa) for Young's modulus ``E`` (MPa) and Poisson ratio ``nu``.

    For ``model="plane-stress"`` ``lam`` is the plane-stress value :math:`E\\nu/(1-\\nu^2)`.
    """
    E = np.asarray(E, dtype=float)
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    if model == "plane-stress":
        lam = 2.0 * lam * mu / (lam + 2.0 * mu)
    return lam, mu


def elasticity_form():
    """Bilinear form :math:`a(u,v)=\\int 2\\mu\\,\\varepsilon(u):\\varepsilon(v)+\\lambda\\,\\mathrm{div}u\\,\\mathrm{div}v`.

    ``lam`` and ``mu`` enter through ``w`` (``asm(form, basis, lam=..., mu=...)``), each a scalar or an array of
    shape ``(n_elements, n_quadrature_points)``.
    """
    from skfem import BilinearForm
    from skfem.helpers import ddot, sym_grad, trace

    @BilinearForm
    def a(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return 2.0 * w["mu"] * ddot(eu, ev) + w["lam"] * trace(eu) * trace(ev)

    return a


# ----------------------------------------------------------------------------------------------------------------
# point location / evaluation
# ----------------------------------------------------------------------------------------------------------------
class _Locator:
    """Point -> (element, reference coordinates) for straight simplices: KD-tree on element centroids gives ``k``
    candidates per point, a vectorised affine inverse picks the one whose barycentric coordinates are >= -tol."""

    def __init__(self, mesh):
        from scipy.spatial import cKDTree

        p, t = mesh.p, mesh.t
        self.dim = p.shape[0]
        self.b = p[:, t[0]].T                                      # (nt, dim)
        A = np.stack([p[:, t[j + 1]] - p[:, t[0]] for j in range(self.dim)], axis=-1).transpose(1, 0, 2)
        self.invA = np.linalg.inv(A)                               # (nt, dim, dim); skfem MappingAffine convention
        self.tree = cKDTree(p[:, t].mean(axis=1).T)
        self.hmax = float(np.max(np.linalg.norm(A, axis=1)))

    def locate(self, x, tol=1e-9):
        """``x`` (n, dim) -> element index (n,) int (-1 outside) and reference coordinates (n, dim)."""
        n = len(x)
        elem = np.full(n, -1, dtype=np.int64)
        X = np.zeros((n, self.dim))
        todo = np.arange(n)
        nt = len(self.b)
        for k in (8, 32, 128):
            if len(todo) == 0:
                break
            k = min(k, nt)
            for s in range(0, len(todo), 65536):
                idx = todo[s:s + 65536]
                _, cand = self.tree.query(x[idx], k=k)
                cand = cand.reshape(len(idx), k)
                d = x[idx, None, :] - self.b[cand]                 # (m, k, dim)
                ref = np.einsum("mkij,mkj->mki", self.invA[cand], d)
                bary_min = np.minimum(ref.min(axis=2), 1.0 - ref.sum(axis=2))
                best = np.argmax(bary_min, axis=1)
                ok = bary_min[np.arange(len(idx)), best] >= -tol
                elem[idx[ok]] = cand[ok, best[ok]]
                X[idx[ok]] = ref[ok, best[ok]]
            todo = todo[elem[todo] < 0]
        return elem, X


# ----------------------------------------------------------------------------------------------------------------
# solution object
# ----------------------------------------------------------------------------------------------------------------
@dataclass
class Solution:
    """FE solution of a forward model.

    Attributes
    ----------
    model : str
        ``"plane-strain"``, ``"plane-stress"`` or ``"3d"``.
    mesh : skfem.MeshTri1 or skfem.MeshTet1
        ``p[0]`` depth x, ``p[1]`` lateral y, (``p[2]`` elevation z) in mm, with named subdomains/boundaries.
    u : (n_dofs,) float
        P2 displacement DOFs (mm), scikit-fem interleaved vector order.
    params : dict
        Every parameter of the solve (moduli MPa, sizes mm, symmetry, mesh sizes).
    info : dict
        ``n_dofs``, ``solve_time_s``, ``mesh_time_s``, ``peak_rss_mb``, ``solver``, ``reaction_force``
        (axial force on the patch, N for 3D of the full block, N/mm for 2D).
    """

    model: str
    mesh: object
    u: np.ndarray
    params: dict
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self._locator = None
        self._basis = None

    # -- internals ------------------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.mesh.p.shape[0]

    @property
    def basis(self):
        """The scalar P2 basis on :attr:`mesh` (vector DOF ``dim*i + c`` is component ``c`` of scalar DOF ``i``)."""
        if self._basis is None:
            from skfem import Basis, ElementTetP2, ElementTriP2
            e = ElementTriP2() if self.dim == 2 else ElementTetP2()
            self._basis = Basis(self.mesh, e, intorder=1)
        return self._basis

    @property
    def symmetry(self) -> str:
        return self.params.get("symmetry", "full") if self.dim == 3 else "full"

    def _eval(self, points, outside, ncoord=2):
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != ncoord:
            axes = "[x depth, y lateral]" if ncoord == 2 else "[x depth, y lateral, z elevation]"
            raise ValueError(f"points must have shape (n, {ncoord}) {axes} in mm, got {pts.shape}")
        if outside not in ("nan", "raise"):
            raise ValueError(f"outside must be 'nan' or 'raise', got {outside!r}")
        if self._locator is None:
            self._locator = _Locator(self.mesh)
        # sgn[:, c]: mirror factors of the coordinates (y, z) mapped onto the modelled part (quarter/half model)
        sgn = np.ones((len(pts), 3))
        if self.dim == 3:
            q = np.zeros((len(pts), 3))
            q[:, :ncoord] = pts
            mirror = {"quarter": (1, 2), "half": (2,), "full": ()}[self.symmetry]
            for c in mirror:
                sgn[:, c] = np.where(q[:, c] < 0, -1.0, 1.0)
                q[:, c] = np.abs(q[:, c])
        else:
            q = pts
        finite = np.all(np.isfinite(q), axis=1)
        elem = np.full(len(q), -1, dtype=np.int64)
        X = np.zeros((len(q), self.dim))
        if np.any(finite):
            e_f, X_f = self._locator.locate(q[finite])
            elem[finite], X[finite] = e_f, X_f
        inside = elem >= 0
        if outside == "raise" and not np.all(inside):
            bad = pts[~inside][0]
            raise ValueError(f"points: {np.sum(~inside)} of {len(pts)} points lie outside the model domain "
                             f"(first: {', '.join(f'{v:g}' for v in bad)} mm)")
        return pts, sgn, elem, X, inside

    def _mirror(self, v, sgn, grad):
        """Apply the reflection(s) of the symmetric model: component c and derivative c flip with sgn[:, c]."""
        d = v.shape[1]
        s = sgn[:, :d]
        if grad:
            return v * s[:, :, None] * s[:, None, :]
        return v * s

    def _values(self, elem, X, grad):
        """Displacement (m, dim) or gradient (m, dim, dim) [component, derivative] at located points."""
        d = self.dim
        eb = self.basis.elem
        dofs = self.basis.element_dofs[:, elem]                    # (n_local, m)
        U = self.u.reshape(-1, d)                                  # (n_scalar_dofs, d)
        out = np.zeros((len(elem), d, d)) if grad else np.zeros((len(elem), d))
        invA = self._locator.invA[elem] if grad else None
        for i in range(dofs.shape[0]):
            phi, dphi = eb.lbasis(X.T, i)
            Ui = U[dofs[i]]                                        # (m, d)
            if grad:
                g = np.einsum("mba,bm->ma", invA, dphi)            # physical gradient of phi_i, (m, d)
                out += Ui[:, :, None] * g[:, None, :]
            else:
                out += Ui * phi[:, None]
        return out

    # -- public ---------------------------------------------------------------------------------------------
    def displacement(self, points, *, outside: str = "nan") -> np.ndarray:
        """Displacement in the imaging plane.

        Parameters
        ----------
        points : (n, 2) float
            ``[x, y]`` mm: x = depth below the top face, y = lateral offset from the centre line.  For ``"3d"`` the
            points lie in the central (imaging) plane z = 0.
        outside : {"nan", "raise"}
            Points outside the model domain give NaN rows (default) or raise ``ValueError``.

        Returns
        -------
        (n, 2) float
            ``[u_x, u_y]`` mm, ``u_x > 0`` pointing deeper (compression pushes the top down).
        """
        pts, sgn, elem, X, inside = self._eval(points, outside)
        out = np.full((len(pts), 2), np.nan)
        if np.any(inside):
            v = self._values(elem[inside], X[inside], grad=False)
            out[inside] = self._mirror(v, sgn[inside], False)[:, :2]
        return out

    def displacement_3d(self, points, *, outside: str = "nan") -> np.ndarray:
        """3D model only: displacement ``(n, 3)`` ``[u_x, u_y, u_z]`` mm at points ``(n, 3)`` ``[x, y, z]`` mm
        anywhere in the block (the symmetric parts are reconstructed by reflection)."""
        if self.dim != 3:
            raise ValueError(f"displacement_3d needs a 3d model, this one is {self.model!r}")
        pts, sgn, elem, X, inside = self._eval(points, outside, ncoord=3)
        out = np.full((len(pts), 3), np.nan)
        if np.any(inside):
            v = self._values(elem[inside], X[inside], grad=False)
            out[inside] = self._mirror(v, sgn[inside], False)
        return out

    def displacement_gradient(self, points, *, outside: str = "nan") -> np.ndarray:
        """In-plane displacement gradient ``(n, 2, 2)``: ``[i, j] = d u_i / d x_j`` with (x, y) as in
        :meth:`displacement`; NaN outside (or ``ValueError`` with ``outside="raise"``)."""
        pts, sgn, elem, X, inside = self._eval(points, outside)
        out = np.full((len(pts), 2, 2), np.nan)
        if np.any(inside):
            g = self._values(elem[inside], X[inside], grad=True)
            out[inside] = self._mirror(g, sgn[inside], True)[:, :2, :2]
        return out

    def strain(self, points, *, outside: str = "nan") -> np.ndarray:
        """Small strain in the imaging plane, ``(n, 3)`` ``[e_xx, e_yy, e_xy]`` with
        ``e_xy = (du_x/dy + du_y/dx) / 2`` (tensor shear, not engineering).  Points on an element interface (e.g.
        the inclusion boundary) take the value of one adjacent element.  NaN outside, as :meth:`displacement`."""
        g = self.displacement_gradient(points, outside=outside)
        return np.stack([g[:, 0, 0], g[:, 1, 1], 0.5 * (g[:, 0, 1] + g[:, 1, 0])], axis=1)

    def region(self, points) -> np.ndarray:
        """Region label per point: 1 inside the inclusion, 0 background, -1 outside the domain."""
        pts, _, elem, _, inside = self._eval(points, "nan")
        lab = np.full(len(pts), -1, dtype=np.int64)
        inc = np.zeros(self.mesh.t.shape[1], dtype=bool)
        inc[self.mesh.subdomains["inclusion"]] = True
        lab[inside] = inc[elem[inside]].astype(np.int64)
        return lab

    def nodal_displacement(self) -> np.ndarray:
        """Displacement at the mesh vertices, ``(dim, n_vertices)`` mm (exact nodal P2 values)."""
        U = self.u.reshape(-1, self.dim)
        return U[self.basis.nodal_dofs[0]].T

    def save(self, path) -> Path:
        """Save to ``.npz`` (reloadable with :func:`load_solution`) or ``.vtu``/``.xdmf`` (meshio, for ParaView:
        the linear mesh with vertex displacement and cell region id).  Returns the path written."""
        path = Path(path)
        region = np.zeros(self.mesh.t.shape[1], dtype=np.int8)
        region[self.mesh.subdomains["inclusion"]] = 1
        if path.suffix.lower() in (".vtu", ".xdmf", ".vtk"):
            from femreg.optional import require

            meshio = require("meshio", extra="forward", feature="Solution.save to VTU/XDMF")
            ctype = "triangle" if self.dim == 2 else "tetra"
            u = self.nodal_displacement().T
            pts = self.mesh.p.T if self.dim == 3 else np.c_[self.mesh.p.T, np.zeros(self.mesh.p.shape[1])]
            disp = u if self.dim == 3 else np.c_[u, np.zeros(len(u))]
            meshio.write(str(path), meshio.Mesh(pts, [(ctype, self.mesh.t.T)], point_data={"displacement": disp},
                                                cell_data={"region": [region.astype(np.int32)]}))
            return path
        if path.suffix.lower() != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        bnames = sorted(self.mesh.boundaries)
        np.savez_compressed(
            path, format=np.array("femreg-forward-solution-1"), model=np.array(self.model), p=self.mesh.p,
            t=self.mesh.t, region=region, u=self.u, params=np.array(json.dumps(self.params)),
            info=np.array(json.dumps(self.info)), boundary_names=np.array(bnames),
            **{f"boundary_{b}": self.mesh.boundaries[b] for b in bnames})
        return path


def load_solution(path) -> Solution:
    """Load a :class:`Solution` written by :meth:`Solution.save` (``.npz``)."""
    from skfem import MeshTet1, MeshTri1

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["format"]) != "femreg-forward-solution-1":
                raise ValueError(f"{path}: not a femreg forward solution")
            p, t, region = z["p"], z["t"], z["region"]
            boundaries = {str(b): z[f"boundary_{b}"] for b in z["boundary_names"]}
            model, u = str(z["model"]), z["u"]
            params, info = json.loads(str(z["params"])), json.loads(str(z["info"]))
    except (KeyError, OSError, ValueError, EOFError) as exc:
        from femreg.errors import FileFormatError
        raise FileFormatError(f"{path}: not a readable femreg forward solution ({exc})") from exc
    Mesh = MeshTri1 if p.shape[0] == 2 else MeshTet1
    # sort_t=False keeps the saved element/vertex order so DOF numbering matches u
    mesh = Mesh(p, t, sort_t=False)
    mesh = mesh.with_subdomains({"background": np.flatnonzero(region == 0),
                                 "inclusion": np.flatnonzero(region == 1)}).with_boundaries(boundaries)
    return Solution(model=model, mesh=mesh, u=u, params=params, info=info)


# ----------------------------------------------------------------------------------------------------------------
# solve
# ----------------------------------------------------------------------------------------------------------------
def _check_params(model, inclusion_modulus, background_modulus, poisson, compression_mm, symmetry):
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    for name, val in [("inclusion_modulus", inclusion_modulus), ("background_modulus", background_modulus)]:
        if val is None or not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name} must be a positive finite Young's modulus (MPa), got {val!r}")
    if poisson is None or not np.isfinite(poisson) or not (-1.0 < poisson < 0.5):
        raise ValueError(f"poisson must lie in (-1, 0.5) (0.5 is incompressible, not supported), got {poisson!r}")
    if compression_mm is None or not np.isfinite(compression_mm):
        raise ValueError(f"compression_mm must be a finite number (mm), got {compression_mm!r}")
    if symmetry not in ("quarter", "half", "full"):
        raise ValueError(f"symmetry must be 'quarter', 'half' or 'full', got {symmetry!r}")


def _linear_solve(K, f, solver):
    if solver == "auto":
        try:
            import pypardiso  # noqa: F401
            solver = "pardiso"
        except ImportError:
            solver = "superlu"
    if solver == "pardiso":
        from femreg.optional import require

        pypardiso = require("pypardiso", feature="solver='pardiso'")
        x = pypardiso.spsolve(sp.csr_matrix(K), f)
        pypardiso.ps.free_memory(everything=True) if hasattr(pypardiso, "ps") else None
        return x, solver
    if solver == "superlu":
        from scipy.sparse.linalg import spsolve
        return spsolve(sp.csc_matrix(K), f), solver
    raise ValueError(f"solver must be 'auto', 'pardiso' or 'superlu', got {solver!r}")


def solve_elasticity(model: str = "plane-strain", *, inclusion_modulus: float = 40.0,
                     background_modulus: float = 10.0, poisson: float = 0.495, block_mm: float = 160.0,
                     inclusion_diameter_mm: float = 15.0, inclusion_depth_mm: float = 30.0,
                     patch_mm: float | None = 50.0, compression_mm: float = 1.0, mesh_size_mm: float | None = None,
                     coarse_size_mm: float | None = None, refine_region_mm: tuple | None = None,
                     symmetry: str = "quarter", bottom: str = "fixed", solver: str = "auto",
                     cache: bool = False) -> Solution:
    """Solve the paper's phantom as plane strain, plane stress or 3D linear elasticity (P2 elements).

    Parameters
    ----------
    model : {"plane-strain", "plane-stress", "3d"}
    inclusion_modulus, background_modulus : float
        Young's moduli, MPa (paper: 40 HI / 20 mHI / 10 HOM / 5 SI inside, 10 outside).
    poisson : float
        Poisson ratio :math:`\\nu` in (-1, 0.5) (paper: 0.495).
    block_mm : float
        Side of the square block / cube, mm (paper: 160).
    inclusion_diameter_mm, inclusion_depth_mm : float
        Inclusion diameter and depth of its centre below the top face, mm (paper: 15, 30).
    patch_mm : float or None
        Width of the (square, in 3D) compression patch centred on the top face, mm; ``None`` = the whole top face.
    compression_mm : float
        Axial displacement prescribed on the patch, mm (positive = into the block).
    mesh_size_mm : float, optional
        Element size in the refined region (imaged area, inclusion; in 3D a slab around the imaging plane), mm.
        Default 0.5 (2D) / 1.0 (3D).
    coarse_size_mm : float, optional
        Element size far from the imaged area, mm.  Default 8 (2D) / 16 (3D).
    refine_region_mm : tuple, optional
        Refined box: 2D ``(depth, half_width)`` default ``(80, 30)``; 3D ``(depth, half_width, half_thickness)``
        default ``(80, 30, 3)``; ``()`` = no box (only the inclusion boundary and patch edges are refined).
    symmetry : {"quarter", "half", "full"}
        3D only: part of the block that is meshed (the quarter model is exact by symmetry and 4x cheaper).
    bottom : {"fixed", "slip"}
        Bottom face clamped (the paper) or sliding (only ``u_x = 0``; lateral rigid motion removed by symmetry
        planes or by fixing the bottom vertex nearest the centre line).  ``"slip"`` with ``patch_mm=None`` gives
        exactly uniaxial stress in a homogeneous block (used by the tests).
    solver : {"auto", "pardiso", "superlu"}
        Sparse direct solver; ``"auto"`` = MKL PARDISO (``pypardiso``) when installed, else SciPy's SuperLU.
    cache : bool
        Look up / store the solution in the disk cache (:func:`cached_solve`).

    Returns
    -------
    Solution
        With ``displacement(points)``, ``strain(points)``, ``save(path)`` and ``info`` (DOFs, timings, memory).

    Raises
    ------
    ValueError
        Naming the bad parameter (non-positive modulus, poisson >= 0.5, inclusion outside the block, ...).
    """
    kwargs = dict(inclusion_modulus=inclusion_modulus, background_modulus=background_modulus, poisson=poisson,
                  block_mm=block_mm, inclusion_diameter_mm=inclusion_diameter_mm,
                  inclusion_depth_mm=inclusion_depth_mm, patch_mm=patch_mm, compression_mm=compression_mm,
                  mesh_size_mm=mesh_size_mm, coarse_size_mm=coarse_size_mm, refine_region_mm=refine_region_mm,
                  symmetry=symmetry, bottom=bottom, solver=solver)
    if cache:
        return cached_solve(model, **kwargs)
    from skfem import Basis, ElementTetP2, ElementTriP2, ElementVector, asm, condense

    from . import geometry

    _check_params(model, inclusion_modulus, background_modulus, poisson, compression_mm, symmetry)
    if bottom not in ("fixed", "slip"):
        raise ValueError(f"bottom must be 'fixed' or 'slip', got {bottom!r}")
    for name, val in [("mesh_size_mm", mesh_size_mm), ("coarse_size_mm", coarse_size_mm)]:
        if val is not None and (not np.isfinite(val) or val <= 0):
            raise ValueError(f"{name} must be a positive element size (mm), got {val!r}")
    h_fine, h_coarse = DEFAULT_MESH[model]
    h_fine = h_fine if mesh_size_mm is None else mesh_size_mm
    h_coarse = max(h_coarse, h_fine) if coarse_size_mm is None else coarse_size_mm
    t0 = time.perf_counter()
    if model == "3d":
        region = (80.0, 30.0, 3.0) if refine_region_mm is None else tuple(refine_region_mm)
        mesh = geometry.mesh_3d(block_mm=block_mm, inclusion_diameter_mm=inclusion_diameter_mm,
                                inclusion_depth_mm=inclusion_depth_mm, patch_mm=patch_mm, mesh_size_mm=h_fine,
                                coarse_size_mm=h_coarse, fine_region_mm=region or None, symmetry=symmetry)
        elem = ElementTetP2()
    else:
        symmetry = "full"
        region = (80.0, 30.0) if refine_region_mm is None else tuple(refine_region_mm)
        mesh = geometry.mesh_2d(block_mm=block_mm, inclusion_diameter_mm=inclusion_diameter_mm,
                                inclusion_depth_mm=inclusion_depth_mm, patch_mm=patch_mm, mesh_size_mm=h_fine,
                                coarse_size_mm=h_coarse, fine_region_mm=region or None)
        elem = ElementTriP2()
    t_mesh = time.perf_counter() - t0
    dim = mesh.p.shape[0]
    ib = Basis(mesh, ElementVector(elem), intorder=2)
    E = np.full(mesh.t.shape[1], float(background_modulus))
    E[mesh.subdomains["inclusion"]] = float(inclusion_modulus)
    lam, mu = lame_parameters(E, poisson, model)
    nq = ib.X.shape[1]
    t1 = time.perf_counter()
    K = asm(elasticity_form(), ib, lam=np.repeat(lam[:, None], nq, 1), mu=np.repeat(mu[:, None], nq, 1))
    t_asm = time.perf_counter() - t1
    # Dirichlet data: bottom clamped, patch axial (u^1 = x component), symmetry planes normal component
    u = ib.zeros()
    if bottom == "fixed":
        D_bottom = ib.get_dofs("bottom").all()
    else:
        D_bottom = [ib.get_dofs("bottom").all("u^1")]
        bverts = np.unique(mesh.facets[:, mesh.boundaries["bottom"]])
        centre = bverts[np.argmin(np.sum(mesh.p[1:, bverts] ** 2, axis=0))]
        if "sym_y" not in mesh.boundaries:
            D_bottom.append(ib.nodal_dofs[1, [centre]])
        if dim == 3 and "sym_z" not in mesh.boundaries:
            D_bottom.append(ib.nodal_dofs[2, [centre]])
            if "sym_y" not in mesh.boundaries:  # rotation about the x axis: fix u_z at a second bottom vertex
                other = bverts[np.argmax(mesh.p[1, bverts])]
                D_bottom.append(ib.nodal_dofs[2, [other]])
        D_bottom = np.concatenate(D_bottom)
    D_patch = ib.get_dofs("patch").all("u^1")
    u[D_patch] = compression_mm
    D = [D_bottom, D_patch]
    if "sym_y" in mesh.boundaries:
        D.append(ib.get_dofs("sym_y").all("u^2"))
    if "sym_z" in mesh.boundaries:
        D.append(ib.get_dofs("sym_z").all("u^3"))
    D = np.unique(np.concatenate(D))
    f = np.zeros(ib.N)
    t2 = time.perf_counter()
    Kc, fc, xc, I = condense(K, f, x=u, D=D)
    x_int, used = _linear_solve(Kc, fc, solver)
    u[I] = x_int
    t_solve = time.perf_counter() - t2
    # reaction: axial force the patch exerts on the block (sum of nodal internal forces on patch x-DOFs)
    r = K @ u
    factor = {"quarter": 4.0, "half": 2.0, "full": 1.0}[symmetry] if dim == 3 else 1.0
    reaction = float(np.sum(r[D_patch])) * factor
    params = dict(model=model, inclusion_modulus=float(inclusion_modulus), background_modulus=float(background_modulus),
                  poisson=float(poisson), block_mm=float(block_mm), inclusion_diameter_mm=float(inclusion_diameter_mm),
                  inclusion_depth_mm=float(inclusion_depth_mm),
                  patch_mm=None if patch_mm is None else float(patch_mm), compression_mm=float(compression_mm),
                  mesh_size_mm=float(h_fine), coarse_size_mm=float(h_coarse), refine_region_mm=list(region),
                  symmetry=symmetry, bottom=bottom, element="P2")
    info = dict(n_dofs=int(ib.N), n_elements=int(mesh.t.shape[1]), n_vertices=int(mesh.p.shape[1]),
                mesh_time_s=t_mesh, assembly_time_s=t_asm, solve_time_s=t_solve,
                total_time_s=time.perf_counter() - t0, solver=used, reaction_force=reaction,
                peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return Solution(model=model, mesh=mesh, u=u, params=params, info=info)


# ----------------------------------------------------------------------------------------------------------------
# cache
# ----------------------------------------------------------------------------------------------------------------
def cache_dir() -> Path:
    """The one cache folder of the simulator (forward solutions under ``/forward``, RF sequences under
    ``/sequences``): ``$FEMREG_CACHE`` if set, else ``~/.cache/femreg``."""
    return Path(os.environ.get("FEMREG_CACHE") or Path.home() / ".cache" / "femreg")


def cache_key(model: str, **kwargs) -> str:
    """Hash of every parameter of a solve (defaults filled in), used as the cache file name."""
    import inspect

    sig = inspect.signature(solve_elasticity)
    full = {k: v.default for k, v in sig.parameters.items() if k not in ("model", "cache")}
    unknown = set(kwargs) - set(full)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)} for solve_elasticity")
    full.update(kwargs)
    full["model"] = model
    full.pop("solver", None)   # the solver does not change the solution beyond round-off
    h_fine, h_coarse = DEFAULT_MESH.get(model, (None, None))
    if full["mesh_size_mm"] is None:
        full["mesh_size_mm"] = h_fine
    full["cache_version"] = CACHE_VERSION
    if model != "3d":
        full["symmetry"] = "full"
    blob = json.dumps({k: (list(v) if isinstance(v, tuple) else v) for k, v in sorted(full.items())},
                      sort_keys=True, default=float)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def cached_solve(model: str = "plane-strain", **kwargs) -> Solution:
    """:func:`solve_elasticity` with a disk cache under :func:`cache_dir` ``/forward``, keyed by a hash of all
    parameters (same keyword arguments as :func:`solve_elasticity`).  A corrupt cache entry is recomputed."""
    kwargs.pop("cache", None)
    key = cache_key(model, **kwargs)
    folder = cache_dir() / "forward"
    path = folder / f"{model}-{key}.npz"
    if path.exists():
        try:
            sol = load_solution(path)
            sol.info["from_cache"] = str(path)
            return sol
        except ValueError:
            path.unlink(missing_ok=True)
    sol = solve_elasticity(model, **kwargs)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_savez(path, writer=sol.save)  # concurrent callers never read a half-written file
    sol.info["cache_path"] = str(path)
    return sol
