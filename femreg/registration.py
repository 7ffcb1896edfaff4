"""``femreg.register``: two-frame FE image registration (eq:objf = eq:IR + R), and its result object.

Convention: ``reference(x) ~ moving(x + u(x))``; images are (axial, lateral) = (x, y) arrays, pixel [i, j] centre
at ``origin + (i dx, j dy)`` mm.  With ``offset=S`` the problem is eq:IR of a sequence:
``I_k(x + S(x)) ~ I_{k+1}(x + S(x) + u(x))`` (reference = I_k, moving = I_{k+1}).

Pipeline: validate -> normalise by the reference RMS (:mod:`femreg.image`) -> spline coefficients (once) ->
mesh (ROI or the user's) -> pixel quadrature -> SSD term (fixed reference gradient, eq:wfnew) + regulariser ->
initial guess (NCC block matching) -> Gauss-Newton (:mod:`femreg.solver`) -> :class:`RegistrationResult`.
"""
from __future__ import annotations

import time

import numpy as np
from skfem import MeshQuad1

from .blockmatch import BlockMatchResult, block_match
from .data_term import SSDTerm
from .errors import InputError
from .image import SplineImage, normalize_pair, pixel_axes, validate_image, validate_spacing
from .mesh import DEFAULT_ELEMENT_SIZE, as_quad_mesh, check_mesh_in_image, roi_mesh
from .pixels import PixelQuadrature, PointLocator
from .scaling import effective_alpha
from .regularizers import Regularizer, available_regularizers, make_regularizer
from .solver import Objective, gauss_newton

__all__ = ["register", "RegistrationResult", "load_result", "ncc", "COARSE_TO_FINE_STRAIN"]

#: Global strain of the block-matching field above which ``register`` adds a coarse pass (``coarse_to_fine``).
COARSE_TO_FINE_STRAIN = 0.01


def ncc(a, b) -> float:
    """Normalised cross-correlation of two equally shaped sample arrays (zero-mean, unit-norm)."""
    a = np.asarray(a, float).ravel() - np.mean(a)
    b = np.asarray(b, float).ravel() - np.mean(b)
    d = np.linalg.norm(a) * np.linalg.norm(b)
    return float(a @ b / d) if d > 0 else 0.0


class RegistrationResult:
    """A registered displacement field on a quad mesh.

    Attributes
    ----------
    mesh : skfem.MeshQuad1
        mm; ``mesh.p[0]`` axial x, ``mesh.p[1]`` lateral y.
    u : (2 n_nodes,) float, mm
        Nodal displacement, interleaved (u[0::2] = ux, u[1::2] = uy), scikit-fem DOF order.
    success, status, message, nit, energy_history
        From the Gauss-Newton solver (:class:`femreg.solver.GaussNewtonResult`).
    regularizer : str
        Name of the regulariser; ``alpha`` its weight (for the RMS-normalised images).
    ncc_before, ncc_after : float
        NCC of reference vs moving over the mesh pixels, at u = 0 and at the result: a quality measure.
    shape, spacing, origin
        Reference pixel grid.
    timings : dict
        Seconds per stage.
    blockmatch : BlockMatchResult or None
        The initial-guess field, if block matching was used.
    """

    def __init__(self, mesh, u, *, shape, spacing, origin, regularizer="", alpha=float("nan"), success=False,
                 status=-1, message="", nit=0, energy_history=(), ncc_before=float("nan"),
                 ncc_after=float("nan"), timings=None, blockmatch=None, solver_result=None, grid=None,
                 locator=None):
        self.mesh = mesh
        self.u = np.asarray(u, float)
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.regularizer = str(regularizer)
        self.alpha = float(alpha)
        self.success = bool(success)
        self.status = int(status)
        self.message = str(message)
        self.nit = int(nit)
        self.energy_history = np.asarray(energy_history, float)
        self.ncc_before = float(ncc_before)
        self.ncc_after = float(ncc_after)
        self.timings = dict(timings or {})
        self.blockmatch = blockmatch
        self.solver_result = solver_result
        self._locator = locator
        self._grid = grid

    # -- sampling -------------------------------------------------------------------------------------------
    @property
    def locator(self) -> PointLocator:
        if self._locator is None:
            self._locator = PointLocator(self.mesh)
        return self._locator

    @property
    def ux(self):
        return self.u[0::2]

    @property
    def uy(self):
        return self.u[1::2]

    def displacement(self, points) -> np.ndarray:
        """u at ``points`` (n, 2) [x, y] mm -> (n, 2) [ux, uy] mm; NaN outside the mesh."""
        pts = np.asarray(points, float).reshape(-1, 2)
        loc = self.locator.locate(pts)
        out = np.full((len(pts), 2), np.nan)
        out[loc.inside, 0] = np.sum(loc.N * self.ux[loc.nodes], axis=1)
        out[loc.inside, 1] = np.sum(loc.N * self.uy[loc.nodes], axis=1)
        return out

    def strain(self, points) -> np.ndarray:
        """Small strain at ``points`` (n, 2) mm -> (n, 3) [exx, eyy, exy], exy = (dux/dy + duy/dx) / 2;
        NaN outside the mesh.  Bilinear elements: strain is discontinuous across element edges (a point on
        an edge takes one of its elements)."""
        pts = np.asarray(points, float).reshape(-1, 2)
        loc = self.locator.locate(pts)
        out = np.full((len(pts), 3), np.nan)
        ux, uy = self.ux[loc.nodes], self.uy[loc.nodes]
        dux = np.einsum("nk,nkd->nd", ux, loc.dN)
        duy = np.einsum("nk,nkd->nd", uy, loc.dN)
        out[loc.inside, 0] = dux[:, 0]
        out[loc.inside, 1] = duy[:, 1]
        out[loc.inside, 2] = 0.5 * (dux[:, 1] + duy[:, 0])
        return out

    def pixel_points(self) -> np.ndarray:
        """Centres of the reference pixels, (n_axial * n_lateral, 2) mm, C order."""
        x, y = pixel_axes(self.shape, self.spacing, self.origin)
        X, Y = np.meshgrid(x, y, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()])

    def on_grid(self) -> dict:
        """ux, uy, exx, eyy, exy on the reference pixel grid, each (n_axial, n_lateral) float64, NaN outside
        the mesh."""
        if self._grid is None:
            x, y = pixel_axes(self.shape, self.spacing, self.origin)
            loc = self.locator.locate_grid(x, y)          # separable on tensor meshes
            g = {k: np.full(self.shape[0] * self.shape[1], np.nan) for k in ("ux", "uy", "exx", "eyy", "exy")}
            ux, uy = self.ux[loc.nodes], self.uy[loc.nodes]
            g["ux"][loc.inside] = np.sum(loc.N * ux, axis=1)
            g["uy"][loc.inside] = np.sum(loc.N * uy, axis=1)
            g["exx"][loc.inside] = np.sum(loc.dN[:, :, 0] * ux, axis=1)
            g["eyy"][loc.inside] = np.sum(loc.dN[:, :, 1] * uy, axis=1)
            g["exy"][loc.inside] = 0.5 * (np.sum(loc.dN[:, :, 1] * ux, axis=1) + np.sum(loc.dN[:, :, 0] * uy, axis=1))
            self._grid = {k: v.reshape(self.shape) for k, v in g.items()}
        return self._grid

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path, **extra) -> None:
        """Write the result as .npz (keys: mesh_points (2, n_nodes), mesh_cells (4, n_el), u, spacing, origin,
        shape, ux, uy, exx, eyy, exy (n_axial, n_lateral), regularizer, alpha, success, nit, message,
        ncc_before, ncc_after, energy_history), plus any ``extra`` arrays."""
        g = self.on_grid()
        np.savez_compressed(
            path, mesh_points=np.asarray(self.mesh.p, float), mesh_cells=np.asarray(self.mesh.t, np.int64),
            u=self.u, spacing=self.spacing, origin=self.origin, shape=np.asarray(self.shape, np.int64),
            ux=g["ux"], uy=g["uy"], exx=g["exx"], eyy=g["eyy"], exy=g["exy"],
            regularizer=np.str_(self.regularizer), alpha=np.float64(self.alpha), success=np.bool_(self.success),
            nit=np.int64(self.nit), message=np.str_(self.message), ncc_before=np.float64(self.ncc_before),
            ncc_after=np.float64(self.ncc_after), energy_history=self.energy_history, **extra)

    def __repr__(self) -> str:
        return (f"RegistrationResult(regularizer={self.regularizer!r}, alpha={self.alpha:g}, "
                f"success={self.success}, nit={self.nit}, n_nodes={self.mesh.p.shape[1]}, "
                f"ncc {self.ncc_before:.3f} -> {self.ncc_after:.3f}, message={self.message!r})")


def load_result(path) -> RegistrationResult:
    """Read a file written by :meth:`RegistrationResult.save`."""
    from .errors import FileFormatError

    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise FileFormatError(f"{path}: not a femreg result file ({exc})") from None
    need = ["mesh_points", "mesh_cells", "u", "spacing", "origin", "shape"]
    missing = [k for k in need if k not in d]
    if missing:
        raise FileFormatError(f"{path}: not a femreg result file (missing {missing})")
    mesh = MeshQuad1(d["mesh_points"], d["mesh_cells"])
    grid = {k: d[k] for k in ("ux", "uy", "exx", "eyy", "exy") if k in d} or None
    if grid is not None and len(grid) < 5:
        grid = None
    return RegistrationResult(
        mesh, d["u"], shape=tuple(d["shape"]), spacing=d["spacing"], origin=d["origin"],
        regularizer=str(d.get("regularizer", "")), alpha=float(d.get("alpha", np.nan)),
        success=bool(d.get("success", False)), nit=int(d.get("nit", 0)), message=str(d.get("message", "")),
        energy_history=d.get("energy_history", ()), ncc_before=float(d.get("ncc_before", np.nan)),
        ncc_after=float(d.get("ncc_after", np.nan)), grid=grid)


def _field_at(spec, mesh, points, what: str):
    """A displacement given as callable(points)->(n,2), nodal vector (2 n_nodes,), or RegistrationResult."""
    n_nodes = mesh.p.shape[1]
    if isinstance(spec, RegistrationResult):
        v = spec.displacement(points)
        return np.nan_to_num(v, nan=0.0)
    if callable(spec):
        v = np.asarray(spec(np.asarray(points, float)), float)
        if v.shape != (len(points), 2):
            raise InputError(f"{what} callable must return shape ({len(points)}, 2), got {v.shape}")
    else:
        arr = np.asarray(spec, float).ravel()
        if arr.size != 2 * n_nodes:
            raise InputError(f"{what} nodal vector must have 2 * n_nodes = {2 * n_nodes} entries, got {arr.size}")
        loc = PointLocator(mesh).locate(points)
        v = np.zeros((len(points), 2))
        v[loc.inside, 0] = np.sum(loc.N * arr[0::2][loc.nodes], axis=1)
        v[loc.inside, 1] = np.sum(loc.N * arr[1::2][loc.nodes], axis=1)
    if not np.all(np.isfinite(v)):
        raise InputError(f"{what} contains NaN/Inf values")
    return v


def _nodal(spec, mesh, what):
    """Nodal interleaved vector from a callable / nodal vector / result / BlockMatchResult."""
    pts = mesh.p.T
    if isinstance(spec, BlockMatchResult):
        v = spec(pts)
    elif not callable(spec) and not isinstance(spec, RegistrationResult):
        arr = np.asarray(spec, float).ravel()
        if arr.size != 2 * mesh.p.shape[1]:
            raise InputError(f"{what} nodal vector must have 2 * n_nodes = {2 * mesh.p.shape[1]} entries, "
                             f"got {arr.size}")
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{what} contains NaN/Inf values")
        return arr.copy()
    else:
        v = _field_at(spec, mesh, pts, what)
    u = np.empty(2 * len(pts))
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return u


def register(reference_image, moving_image, *, spacing, origin=(0.0, 0.0), regularizer="momentum-stress",
             alpha=None, mesh=None, element_size=None, margin=None, initial="blockmatch", offset=None,
             maxiter: int = 20, tol: float = 1e-3, linear_solver: str = "splu", blockmatch_options=None,
             regularizer_options=None, normalize: bool = True, callback=None, allow_mesh_outside: bool = False,
             coarse_to_fine="auto") -> RegistrationResult:
    """Register ``moving_image`` to ``reference_image``: find u minimising eq:objf = psi (eq:IR) + R[u].

    Parameters
    ----------
    reference_image, moving_image : (n_axial, n_lateral) array
        I_1 and I_2 (RF or any intensity), same shape.  Convention: reference(x) ~ moving(x + u(x)).
    spacing : (dx, dy) mm
        Pixel spacing (axial, lateral); a scalar means square pixels.
    origin : (2,) mm
        Centre of pixel [0, 0].
    regularizer : str or Regularizer
        A name from :func:`femreg.regularizers.available_regularizers`: "momentum-stress" = R_P_sigma (default,
        the most accurate laterally in the paper and here), "momentum-strain" = R_P_eps, "strain" = R_eps,
        "strain-incompressible" = R_eps_i; or a Regularizer instance (e.g. from ``regularizers.from_form``).
    alpha : float or "auto", optional
        :math:`\\alpha` of the regulariser (eq:objf) for RMS-normalised images; "auto" = chosen from the pair by
        :func:`femreg.autoalpha.choose_alpha` (UPRE, several registrations); None = the regulariser's
        documented default (R_eps 30, R_eps_i 3 with the default 2 mm mesh; see
        :mod:`femreg.regularizers.strain`).
    mesh : skfem.MeshQuad1, meshio.Mesh or path, optional
        A user's quad mesh (mm, [x, y]); default: structured ROI mesh (:func:`femreg.mesh.roi_mesh`).
    element_size, margin : float or (2,) mm, optional
        For the default ROI mesh (defaults :data:`femreg.mesh.DEFAULT_ELEMENT_SIZE` / ``DEFAULT_MARGIN``).
    initial : "blockmatch" | "zero" | callable | (2 n_nodes,) array | RegistrationResult | BlockMatchResult
        Initial guess u_1: NCC block matching (paper), zero, a field callable(points (n,2)) -> (n,2) mm, or
        nodal values on the mesh (e.g. from an earlier increment).
    offset : callable | (2 n_nodes,) array | RegistrationResult, optional
        S of eq:IR: both images are sampled at x + S(x) (sequence tracking); None = 0.
    maxiter, tol
        Gauss-Newton stopping rule: ``maxiter`` iterations or ``||du|| / ||u|| < tol`` (paper 20, 1e-3).
    linear_solver : {"splu", "spsolve", "amg-cg"}
    blockmatch_options : dict, optional
        Keyword arguments of :func:`femreg.blockmatch.block_match` (window, overlap, search, subsample, ...).
    regularizer_options : dict, optional
        Extra keyword arguments of the regulariser factory.
    normalize : bool
        Divide both images by the reference RMS (default; makes alpha scale-free).
    callback : callable(u, info), optional
        Called after each Gauss-Newton iteration.
    coarse_to_fine : "auto" | bool
        Large strain: register first on a mesh 3x coarser (from the block-matching start), then use that field as
        the initial guess.  At more than ~1 % strain the integer-pixel block matching is wrong in places and
        Gauss-Newton converges one RF period off there; the coarse pass averages over many more pixels and is
        not fooled (3D SI frames 1 -> 10, 1.4 % strain: total strain error 349 % -> 11 %).  "auto" (default) does it
        when the block-matching field's global strain exceeds :data:`COARSE_TO_FINE_STRAIN` and there is no
        ``offset``; True always (with block matching), False never.
    allow_mesh_outside : bool
        Accept a mesh whose nodes partly leave the image (elements there are held by the regulariser alone);
        :func:`femreg.track` uses it for meshes moved with the tissue.  At least one pixel must lie inside.

    Returns
    -------
    RegistrationResult
    """
    if isinstance(alpha, str):          # alpha="auto": chosen from the pair alone (femreg.autoalpha)
        kw = {k: v for k, v in locals().items() if k not in ("reference_image", "moving_image")}
        from .autoalpha import register_auto
        return register_auto(reference_image, moving_image, **kw)
    t_all = time.perf_counter()
    timings = {}
    ref = validate_image(reference_image, "reference image")
    mov = validate_image(moving_image, "moving image")
    if ref.shape != mov.shape:
        raise InputError(f"image shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    spacing, origin = validate_spacing(spacing, origin)
    if not isinstance(regularizer, (str, Regularizer)):
        raise InputError(f"regularizer must be a name or a Regularizer, got {type(regularizer).__name__}")
    if isinstance(regularizer, str) and regularizer not in available_regularizers():
        raise InputError(f"unknown regularizer {regularizer!r}; choose one of {available_regularizers()}")
    try:
        reg = make_regularizer(regularizer, alpha=alpha, **(regularizer_options or {}))
    except InputError:
        raise
    except (ValueError, TypeError) as exc:
        raise InputError(str(exc)) from None
    if int(maxiter) < 0 or not (np.isfinite(tol) and tol > 0):
        raise InputError(f"need maxiter >= 0 and tol > 0, got maxiter={maxiter}, tol={tol}")

    t = time.perf_counter()
    if normalize:
        ref, mov, _ = normalize_pair(ref, mov)
    I1 = SplineImage(ref, spacing, origin)
    I2 = SplineImage(mov, spacing, origin)
    timings["prefilter"] = time.perf_counter() - t

    t = time.perf_counter()
    if mesh is None:
        fe_mesh = roi_mesh(ref.shape, spacing, origin, element_size=element_size, margin=margin)
    else:
        fe_mesh = as_quad_mesh(mesh)
    if not allow_mesh_outside:
        check_mesh_in_image(fe_mesh, ref.shape, spacing, origin)
    locator = PointLocator(fe_mesh)
    quad = PixelQuadrature(fe_mesh, ref.shape, spacing, origin, locator=locator)
    if quad.n_pixels == 0:
        raise InputError("mesh outside the image: no pixel centre lies inside the mesh")
    S = None if offset is None else _field_at(offset, fe_mesh, quad.points, "offset")
    data = SSDTerm(quad, I1, I2, offset=S)
    timings["operator"] = time.perf_counter() - t

    t = time.perf_counter()
    if reg is regularizer:             # never change the caller's instance
        import copy
        reg = copy.copy(reg)
    user_alpha = reg.alpha
    reg.alpha = effective_alpha(user_alpha, fe_mesh)   # alpha per 2 x 2 mm element (femreg.scaling)
    reg.setup(fe_mesh)
    timings["regularizer_setup"] = time.perf_counter() - t

    t = time.perf_counter()
    bm = None
    n_dof = 2 * fe_mesh.p.shape[1]
    if isinstance(initial, str):
        if initial == "zero":
            u0 = np.zeros(n_dof)
        elif initial == "blockmatch":
            if S is None:
                a, b = ref, mov
            else:  # match I_k(x + S) against I_{k+1}(x + S) on the pixel grid
                pts = RegistrationResult(fe_mesh, np.zeros(n_dof), shape=ref.shape, spacing=spacing,
                                         origin=origin).pixel_points()
                Sg = _field_at(offset, fe_mesh, pts, "offset") if not callable(offset) else offset(pts)
                Sg = np.nan_to_num(np.asarray(Sg, float))
                a = I1(pts + Sg).reshape(ref.shape)
                b = I2(pts + Sg).reshape(ref.shape)
            bm = block_match(a, b, spacing, origin, **(blockmatch_options or {}))
            u0 = _nodal(bm, fe_mesh, "initial")
            if offset is None and (coarse_to_fine is True or (
                    coarse_to_fine == "auto" and bm.global_strain() > COARSE_TO_FINE_STRAIN)):
                h = np.broadcast_to(np.asarray(DEFAULT_ELEMENT_SIZE if element_size is None else element_size,
                                               float), (2,))
                coarse = register(ref, mov, spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                                  element_size=tuple(3.0 * h), margin=margin, initial=bm, maxiter=maxiter,
                                  tol=tol, linear_solver=linear_solver, regularizer_options=regularizer_options,
                                  normalize=False, coarse_to_fine=False)
                pts = fe_mesh.p.T
                v = coarse.displacement(pts)
                miss = ~np.isfinite(v[:, 0])
                v[miss] = bm(pts[miss])          # nodes beyond the coarse mesh keep the block-matching value
                u0 = np.empty(n_dof)
                u0[0::2], u0[1::2] = v[:, 0], v[:, 1]
                reg.setup(fe_mesh)               # the coarse pass set up a shared instance on its own mesh
                timings["coarse_pass"] = coarse.timings.get("total", np.nan)
        else:
            raise InputError(f"initial must be 'blockmatch', 'zero', a callable or a nodal vector, got {initial!r}")
    else:
        if isinstance(initial, BlockMatchResult):
            bm = initial
        u0 = _nodal(initial, fe_mesh, "initial")
    timings["initial"] = time.perf_counter() - t

    t = time.perf_counter()
    obj = Objective(data, reg)
    ncc0 = ncc(data.warped_moving(np.zeros(n_dof)), data.ref_values)
    gn = gauss_newton(obj, u0, maxiter=maxiter, tol=tol, linear_solver=linear_solver, callback=callback)
    ncc1 = ncc(data.residual(gn.x) + data.ref_values, data.ref_values)   # cached residual at the best iterate
    timings["gauss_newton"] = time.perf_counter() - t
    timings["per_iteration"] = list(gn.timings)
    timings["total"] = time.perf_counter() - t_all
    return RegistrationResult(fe_mesh, gn.x, shape=ref.shape, spacing=spacing, origin=origin,
                              regularizer=reg.name, alpha=user_alpha, success=gn.success, status=gn.status,
                              message=gn.message, nit=gn.nit, energy_history=gn.energy_history,
                              ncc_before=ncc0, ncc_after=ncc1, timings=timings, blockmatch=bm,
                              solver_result=gn, locator=locator)
