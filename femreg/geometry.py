"""Curved-array geometries (convex and phased/sector probes): RF frames sampled along diverging rays, registered
in physical Cartesian coordinates.  The mappings (:class:`Convex`, :class:`Sector`, and :class:`Swept` for the
volumes of swept probes, :mod:`femreg.swept`) live in :mod:`femreg.probes` and are re-exported here.

Conventions
-----------
A frame is an ``(n_samples, n_rays)`` array: sample ``[i, j]`` lies on ray ``j`` at range
``r_i = r_0 + i dr`` mm, the range measured from the probe face along the ray (``r_0 = origin[0]``, ``dr =
spacing[0]``).  Ray ``j`` has the angle ``theta_j = (j - (n_rays - 1) / 2) dtheta`` (rays centred on 0,
``dtheta`` = the geometry's angle pitch); angle 0 is the probe axis (x, depth) and a positive angle turns
towards +y.  The apex (centre of curvature) lies ``R = radius_mm`` behind the face at ``(x, y) = (-R, 0)``
(:class:`Convex`); a phased array (:class:`Sector`) has its apex on the face (``R = 0``).  The physical position
of a sample is ``x = (R + r) cos(theta) - R``, ``y = (R + r) sin(theta)`` (mm): the face point of the central
ray is the origin, x depth, y lateral, as for a linear array.

Registration (:func:`register_beam`, reached through ``femreg.register(..., geometry=...)``)
--------------------------------------------------------------------------------------------
The image stage keeps each frame on its (range, angle) sample grid with its cubic B-spline coefficients
(:class:`femreg.image.SplineImage` with spacing ``(dr, dtheta)``); the geometry maps physical points to fractional
sample indices, so the warp I_2(x + u) of eq:IR evaluates the spline at the mapped indices, and the fixed
reference gradient of eq:wfnew is the knot gradient in (r, theta) rotated to (x, y) by the inverse Jacobian.
The mesh is a quad mesh in physical space whose nodes are the physical positions of a (range, angle) lattice
(an annular sector); every sample is a quadrature point at its physical position with the weight of the
physical area it represents, ``(R + r) dr dtheta`` (the polar area element), and is located in the mesh by the
general (non-tensor) path of :class:`femreg.pixels.PointLocator` (the mesh has the logical structure of a
tensor mesh, so its Newton walk, falling back to the KD-tree search).

Initial guess: the whole linear pipeline of :func:`femreg.register` (pyramid, Gauss-Newton, peak-hopping repair)
run in sample space, where the frame is treated as a linear image of spacing ``(dr, rho_c dtheta)`` mm
(``rho_c`` the apex distance of the middle sample), on a tensor mesh whose nodes are the same (range, angle)
lattice; its nodal displacement ``(u_r, u_s)`` is carried to physical space exactly through the mapping,
``u(node) = T(r + u_r, (s + u_s) / rho_c) - T(r, s / rho_c)``.  The final Gauss-Newton solve then minimises
eq:objf on the physical mesh, so the regulariser sees physical displacements and strains; with the default alpha,
its weight is the default times :func:`beam_alpha_factor` of the line spacing at ``rho_c`` (1 up to 0.3 mm lines),
scaled down for pulses longer than the paper probe's (the frame's RF period and lateral speckle cell).

Adaptive refinement (``refine="auto" | N | Refinement(...)``, off by default here: docs/geometry.md): the physical
mesh carries its (range, angle) lattice (:class:`femreg.refine.LogicalGrid`), so :func:`femreg.refine.refine_passes`
marks the jumps of A[u] across the physical edges, splits rows (range) and columns (between rays) of the lattice
and maps the refined lattice; each pass is a physical solve with the unrefined mesh's weight of eq:objf
(:func:`femreg.scaling.refined_alpha`), and a refined result that fails its check gives way to the unrefined one.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
import time

import numpy as np
from scipy import ndimage
from skfem import MeshQuad1

from .data_term import SSDTerm
from .errors import InputError, pass_as
from .orientation import OrientationError, override
from .image import SplineImage, normalize_pair
from .mesh import as_quad_mesh
from .pixels import PixelQuadrature, PointLocator
from .probes import Convex, Sector, Swept, as_geometry
from .result import RegistrationResult, nodal_values, register_beam_result
from .sampling import sample_points

__all__ = ["as_geometry", "beam_strain", "BeamResult", "BeamQuadrature", "BeamSSDTerm",
           "register_beam", "frame_grid", "has_strain_feature", "to_cartesian", "to_sample_displacement"]


def beam_strain(strain, angle) -> np.ndarray:
    """Rotate small strains (n, 3) [exx, eyy, exy] into the beam's frame at ray angles ``angle`` (n,) rad:
    (n, 3) [e_rr (along the ray), e_tt (across), e_rt] with e' = R^T E R, R = [[c, -s], [s, c]]."""
    e = np.asarray(strain, float).reshape(-1, 3)
    c, s = np.cos(angle), np.sin(angle)
    exx, eyy, exy = e[:, 0], e[:, 1], e[:, 2]
    return np.column_stack([c * c * exx + 2 * c * s * exy + s * s * eyy,
                            s * s * exx - 2 * c * s * exy + c * c * eyy,
                            c * s * (eyy - exx) + (c * c - s * s) * exy])


# -- the image term on samples along rays -----------------------------------------------------------------------
class BeamQuadrature(PixelQuadrature):
    """The samples of a beam frame as quadrature points of eq:IR: each at its physical position with the weight
    of its polar area element ``(R + r) dr dtheta`` mm^2, located in a physical quad mesh by the general path of
    :class:`~femreg.pixels.PointLocator` (never the tensor fast paths: ``location.grid`` is None, ``block``
    None)."""

    weights_constant = False

    def __init__(self, mesh, shape, spacing, origin, geometry: Convex, locator: PointLocator | None = None):
        self.mesh = mesh
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.geometry = geometry
        self.locator = locator or PointLocator(mesh)
        X, Y = geometry.sample_positions(self.shape, self.spacing, self.origin)
        pts = np.column_stack([X.ravel(), Y.ravel()])
        lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
        cand = np.flatnonzero(np.all((pts >= lo - 1e-9) & (pts <= hi + 1e-9), axis=1))
        loc = self.locator.locate(pts[cand])
        self.location = loc
        self.block = None
        self.axes = None
        self.index = cand[loc.inside]
        self._points = pts[self.index]
        rho = geometry.radius_mm + self.origin[0] + (self.index // self.shape[1]) * self.spacing[0]
        self.weights = rho * self.spacing[0] * geometry.pitch_rad
        self.n_nodes = mesh.p.shape[1]
        self._P = None
        self._PT = None


class BeamSSDTerm(SSDTerm):
    """:class:`femreg.data_term.SSDTerm` on a :class:`BeamQuadrature`: I_2 sampled at the sample indices of the
    physical points x + u (the geometry's inverse mapping), the fixed reference gradient (eq:wfnew) the knot
    gradient in (r, theta) times the inverse Jacobian, grad_x I = J^{-T} (dI/dr, dI/dtheta)."""

    def __init__(self, quad: BeamQuadrature, reference: SplineImage, moving: SplineImage):
        self.quad = quad
        self.moving = moving
        self.geometry = quad.geometry
        self.offset = None
        self._ref_gradient = None
        self._knots = True
        self._moving_values = moving.data.ravel()[quad.index]
        self._inv_sp = 1.0 / moving.spacing
        gr, gt = reference.gradient_at_pixels()          # dI/dr per mm, dI/dtheta per rad
        gr, gt = gr.ravel()[quad.index], gt.ravel()[quad.index]
        ir = quad.index // quad.shape[1]
        th = self.geometry.angles(quad.shape[1])[quad.index % quad.shape[1]]
        rho = self.geometry.radius_mm + quad.origin[0] + ir * quad.spacing[0]
        c, s = np.cos(th), np.sin(th)
        self._gx = np.ascontiguousarray(c * gr - s * gt / rho)
        self._gy = np.ascontiguousarray(s * gr + c * gt / rho)
        self.ref_values = reference.data.ravel()[quad.index]
        self._bx = self._by = None
        self._bxr = self._byc = np.empty(0)
        self.w = quad.weights
        self._J = None
        self._H = None
        self._cache_u = None
        self._cache_r = None
        self._grid = None
        self._empty = np.empty(0)

    def _index_at(self, u):
        P = self.quad.P
        pts = self.quad.points + np.column_stack([P @ u[0::2], P @ u[1::2]])
        return self.geometry.physical_to_index(pts, self.quad.shape, self.quad.spacing, self.quad.origin)

    @property
    def base_index(self):
        idx = self._index_at(np.zeros(2 * self.quad.n_nodes))
        return idx[0], idx[1]

    def outside_mask(self, u) -> np.ndarray:
        """(m,) bool: samples that ``u`` maps less than 1 sample from the first or 2 from the last sample of
        either axis of the moving frame."""
        idx = self._index_at(np.asarray(u, float))
        hi = (self.moving.shape[0] - 2.0, self.moving.shape[1] - 2.0)
        return (idx[0] < 1.0) | (idx[0] > hi[0]) | (idx[1] < 1.0) | (idx[1] > hi[1])

    def warped_moving(self, u):
        """I_2(x + u(x)) at the quadrature samples, (m,)."""
        if not np.any(u):
            return self._moving_values.copy()
        return self.moving.at_index(self._index_at(np.asarray(u, float)))

    def _warp_compiled(self, u, sub):
        v = self.warped_moving(u)
        if sub.size:
            v -= sub
        return v


# -- meshes and the result ---------------------------------------------------------------------------------------
def _beam_coords(mesh_s, rho_c):
    """Nodes of a sample-space mesh (r mm, s = rho_c theta mm) -> (r, theta)."""
    return mesh_s.p[0], mesh_s.p[1] / rho_c


def physical_mesh(mesh_s, geometry: Convex, rho_c: float) -> MeshQuad1:
    """The physical annular-sector mesh with the nodes of ``mesh_s`` (a mesh in (r, rho_c theta) mm) mapped by
    the geometry; same node numbering and connectivity."""
    r, th = _beam_coords(mesh_s, rho_c)
    x, y = geometry.to_physical(r, th)
    return MeshQuad1(np.vstack([x, y]), mesh_s.t.copy())


def to_physical_displacement(mesh_s, u_s, geometry: Convex, rho_c: float) -> np.ndarray:
    """A sample-space nodal displacement (u_r, u_s) mm on ``mesh_s`` -> the physical nodal displacement of the
    same nodes, exactly through the mapping: T(r + u_r, (s + u_s) / rho_c) - T(r, s / rho_c)."""
    r, th = _beam_coords(mesh_s, rho_c)
    x0, y0 = geometry.to_physical(r, th)
    x1, y1 = geometry.to_physical(r + u_s[0::2], th + u_s[1::2] / rho_c)
    u = np.empty_like(np.asarray(u_s, float))
    u[0::2], u[1::2] = x1 - x0, y1 - y0
    return u


@dataclass(frozen=True)
class _Lattice:
    """The (r, s = rho_c theta) lattice of a beam frame's physical mesh, as :class:`femreg.refine.LogicalGrid`
    wants it (methods of a plain object, so that a result's mesh pickles)."""

    geometry: Convex
    rho_c: float

    def angle(self, q):
        """Ray angle (rad) of logical points (2, n)."""
        return np.asarray(q)[1] / self.rho_c

    def to_physical(self, mesh_s):
        return physical_mesh(mesh_s, self.geometry, self.rho_c)

    def to_logical(self, p):
        r, th = self.geometry.to_beam(p[:, 0], p[:, 1])
        return np.stack([r, self.rho_c * th])


class BeamResult(RegistrationResult):
    """A :class:`~femreg.result.RegistrationResult` of a beam (convex / sector) frame: mesh, u and strains in
    physical Cartesian coordinates (x depth, y lateral, mm); ``shape``, ``spacing``, ``origin`` describe the
    sample grid (``spacing[0]`` = dr mm, ``origin[0]`` = range of the first sample), ``geometry`` the mapping.
    The "pixel grid" is the sample lattice: :meth:`pixel_points` are the samples' physical positions and
    :meth:`on_grid` gives every field at them, (n_samples, n_rays) each.  ``sample_space`` holds the sample-space
    registration of the initial guess."""

    def __init__(self, *args, geometry: Convex, sample_space=None, **kw):
        super().__init__(*args, **kw)
        self.geometry = geometry
        self.sample_space = sample_space

    def _recovery_blends(self) -> bool:
        """:attr:`recovery_weight` blends in the projection (:func:`femreg.fields.adaptive_weight` of
        :func:`femreg.fields.strain_roughness`) where the element strains of an unrefined result hold a feature
        (:func:`has_strain_feature`); elsewhere 0, the nodal average.  The average read a stiff disk's contrast
        10 % weak on a coarse fan (``benchmarks/elastogram_convex.py``, docs/geometry.md); on uniform fans the
        projection only spreads the registration's own defects (sector 1 % +0.3 points).  A refined result keeps
        the average: its elements fit the noise of a uniform fan past the feature test (sector 0.3 deg 1 % 4.04 ->
        4.74 % with the blend)."""
        if getattr(self, "refinement", None) is not None:
            return False
        from .fields import element_strains

        return has_strain_feature(element_strains(self.mesh.p, self.mesh.t, self.u)[:, 0])

    def pixel_points(self) -> np.ndarray:
        X, Y = self.geometry.sample_positions(self.shape, self.spacing, self.origin)
        return np.column_stack([X.ravel(), Y.ravel()])

    def sample_positions(self) -> tuple:
        """Physical positions ``(X, Y)`` of the samples, (n_samples, n_rays) mm each (for pcolormesh)."""
        return self.geometry.sample_positions(self.shape, self.spacing, self.origin)

    def strain(self, points, strain: str = "recovered", frame: str = "xy") -> np.ndarray:
        """Small strain at physical ``points`` (n, 2) mm: ``frame="xy"`` (n, 3) [exx, eyy, exy] as
        :meth:`RegistrationResult.strain`; ``frame="beam"`` [e_rr, e_tt, e_rt] along and across the local ray
        (:func:`beam_strain`)."""
        if frame not in ("xy", "beam"):
            raise InputError(f"frame must be 'xy' or 'beam', got {frame!r}")
        e = super().strain(points, strain)
        return beam_strain(e, self.geometry.ray_angle(points)) if frame == "beam" else e

    def on_grid(self, strain: str = "recovered", frame: str = "xy") -> dict:
        """ux, uy (mm) and the strains at every sample, (n_samples, n_rays) each, NaN outside the mesh; with
        ``frame="beam"`` also err, ett, ert (along / across the ray)."""
        key = (strain, frame)
        cache = self.__dict__.setdefault("_beam_grids", {})
        if key not in cache:
            pts = self.pixel_points()
            u = self.displacement(pts)
            e = RegistrationResult.strain(self, pts, strain)
            out = dict(ux=u[:, 0], uy=u[:, 1], exx=e[:, 0], eyy=e[:, 1], exy=e[:, 2])
            if frame == "beam":
                b = beam_strain(e, self.geometry.ray_angle(pts))
                out.update(err=b[:, 0], ett=b[:, 1], ert=b[:, 2])
            cache[key] = {k: v.reshape(self.shape) for k, v in out.items()}
        return cache[key]

    def save(self, path, **extra):
        extra.setdefault("geometry_kind", np.array(self.geometry.kind))
        extra.setdefault("geometry_radius_mm", np.array(float(self.geometry.radius_mm)))
        extra.setdefault("geometry_angle_pitch_deg", np.array(float(self.geometry.angle_pitch_deg)))
        return super().save(path, **extra)


#: Spread of the element axial strains, ``(p90 - p10) / |median|``, from which a beam frame's strain holds a
#: feature (measured on ``benchmarks/convex_refine.py``'s 58 pairs: uniform fans 0.002-0.038, inclusions and
#: bending 0.125-1.24).
STRAIN_FEATURE_SPREAD = 0.07


def has_strain_feature(exx) -> bool:
    """Whether element axial strains ``exx`` (n_el,) vary by more than noise about a uniform strain:
    ``(p90 - p10) / |median| >= STRAIN_FEATURE_SPREAD`` (finite values only; False where the median is 0)."""
    x = np.asarray(exx, float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return False
    med = abs(float(np.median(x)))
    p10, p90 = np.percentile(x, [10.0, 90.0])
    return bool(med > 0.0 and (p90 - p10) / med >= STRAIN_FEATURE_SPREAD)


def sample_space(geometry: Convex, shape, dr: float, r0: float) -> tuple:
    """The sample-space frame of a beam frame of ``shape`` (n_samples, n_rays): ``(rho_c, spacing, origin)`` with
    ``rho_c`` mm the apex distance of the middle sample, spacing ``(dr, rho_c dtheta)`` mm and origin ``(r0,
    s0)`` mm (rays centred on s = 0): where the frame is a linear image (module docstring)."""
    rho_c = geometry.radius_mm + r0 + 0.5 * (shape[0] - 1) * dr
    ds = rho_c * geometry.pitch_rad
    return rho_c, (dr, ds), (r0, -0.5 * (shape[1] - 1) * ds)


register_beam_result(BeamResult)


#: Pixels of :func:`frame_grid` between two rays at the middle sample: at one, the fan's edges and the
#: interpolated speckle drew in steps half a millimetre wide (40 rays 0.6 deg apart, R 40 mm).
GRID_PIXELS_PER_RAY = 4


def frame_grid(geometry: Convex, shape, dr: float, r0: float) -> tuple:
    """The Cartesian pixel grid that holds a beam frame of ``shape`` (n_samples, n_rays), range step ``dr`` mm,
    first range ``r0`` mm: ``(grid_shape, spacing, origin)``, spacing ``(dr, ds)`` mm, the range step axially and
    laterally the rays' distance at the middle sample (``rho_c dtheta``, :func:`sample_space`) over
    :data:`GRID_PIXELS_PER_RAY` (not below ``dr``), the origin the corner of the fan's bounding box (x depth, y
    lateral, mm)."""
    rho_c, (_, ds), _ = sample_space(geometry, shape, dr, r0)
    ds = max(ds / GRID_PIXELS_PER_RAY, float(dr))
    X, Y = geometry.sample_positions(shape, (dr, geometry.angle_pitch_deg), (r0, 0.0))
    # symmetric about the probe axis (rays centred on angle 0): the grid's middle column lies on y = 0
    half = int(np.ceil(float(np.max(np.abs(Y))) / ds - 1e-9))
    x0 = float(np.min(X))
    nx = int(np.floor((float(np.max(X)) - x0) / dr + 1e-9)) + 1
    return (nx, 2 * half + 1), (float(dr), float(ds)), (x0, -half * float(ds))


def to_cartesian(values, geometry: Convex, dr: float, r0: float, grid, order: int = 1) -> np.ndarray:
    """Scan conversion: ``values`` on a beam frame's samples (n_samples, n_rays), or a stack (n, n_samples,
    n_rays), -> the Cartesian ``grid`` = ``(grid_shape, spacing, origin)`` (:func:`frame_grid`), interpolated at
    each pixel's fractional sample index (``order`` 1: bilinear in (r, theta)); NaN outside the fan and where an
    interpolated neighbour is NaN.  Returns float, shape ``grid_shape`` or ``(n,) + grid_shape``."""
    v = np.asarray(values, float)
    stack = v if v.ndim == 3 else v[None]
    gshape, (dx, dy), (x0, y0) = grid
    X, Y = np.meshgrid(x0 + dx * np.arange(gshape[0]), y0 + dy * np.arange(gshape[1]), indexing="ij")
    shape = stack.shape[1:]
    idx = geometry.physical_to_index(np.column_stack([X.ravel(), Y.ravel()]), shape,
                                     (dr, geometry.angle_pitch_deg), (r0, 0.0))
    inside = ((idx[0] >= -1e-9) & (idx[0] <= shape[0] - 1 + 1e-9) & (idx[1] >= -1e-9)
              & (idx[1] <= shape[1] - 1 + 1e-9))
    out = np.full((stack.shape[0], X.size), np.nan)
    for k, img in enumerate(stack):
        out[k, inside] = ndimage.map_coordinates(img, idx[:, inside], order=order, mode="nearest")
    out = out.reshape((stack.shape[0],) + tuple(gshape))
    return out if v.ndim == 3 else out[0]


def to_sample_displacement(ux, uy, geometry: Convex, dr: float, r0: float, ds: float) -> tuple:
    """A physical displacement (ux, uy) mm at a beam frame's samples (each (n_samples, n_rays), range step ``dr``
    mm, first range ``r0`` mm; NaN allowed) -> the same motion in sample space, ``(u_r, u_s)`` mm with ``s =
    rho_c theta``: the fractional sample index of the moved point minus the sample's own, times ``(dr, ds)``
    (``ds = rho_c dtheta`` of the frame's :func:`sample_space`)."""
    ux, uy = (np.asarray(a, float) for a in (ux, uy))
    shape = ux.shape
    sp = (dr, geometry.angle_pitch_deg)
    X, Y = geometry.sample_positions(shape, sp, (r0, 0.0))
    idx = geometry.physical_to_index(np.column_stack([(X + ux).ravel(), (Y + uy).ravel()]), shape, sp, (r0, 0.0))
    i, j = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    return (idx[0].reshape(shape) - i) * dr, (idx[1].reshape(shape) - j) * ds


# -- the registration ------------------------------------------------------------------------------------------
def beam_spacing(spacing, geometry: Convex, origin):
    """Validate ``spacing`` (dr mm, or (dr mm, dtheta deg) equal to the geometry's pitch) and ``origin``
    ((r_0 mm, 0)); return ``(dr, r0)``."""
    sp = np.atleast_1d(np.asarray(spacing, float)).ravel()
    if sp.size not in (1, 2) or not np.all(np.isfinite(sp)) or sp[0] <= 0:
        raise InputError(f"with a {geometry.kind} geometry, spacing is dr mm or (dr mm, dtheta deg), got {spacing!r}")
    if sp.size == 2 and not np.isclose(sp[1], geometry.angle_pitch_deg, rtol=1e-6):
        raise InputError(f"spacing[1] = {sp[1]:g} deg differs from the geometry's angle pitch "
                         f"{geometry.angle_pitch_deg:g} deg")
    org = np.asarray(origin, float).ravel()
    if org.size != 2 or not np.all(np.isfinite(org)) or org[1] != 0:
        raise InputError(f"with a {geometry.kind} geometry, origin is (range of the first sample mm, 0): rays "
                         f"are centred on angle 0; got {origin!r}")
    if geometry.radius_mm + org[0] <= 0:
        raise InputError(f"the first sample lies at or behind the apex (range {org[0]:g} mm, radius "
                         f"{geometry.radius_mm:g} mm)")
    return float(sp[0]), float(org[0])


#: Line spacing (mm) at which the default alphas hold: the paper probe's lines (femreg/data/default_alphas.json).
REFERENCE_LINE_SPACING = 0.3
#: Axial RF period (mm, :func:`femreg.speckle.rf_period`) at which the default alphas hold: the paper probe's
#: 5.5 MHz at 1540 m/s (its frames read 0.139-0.140 mm).
REFERENCE_RF_PERIOD = 0.14
#: Lateral speckle cell (lines, :func:`lateral_cell_lines`) of the simulated fans on which the power below was
#: measured (3 line spacings per beam at 0.45-0.6 degrees: 2.7-2.9 lines).
REFERENCE_CELL_LINES = 2.8
#: Power of the line spacing in :func:`beam_alpha_factor` (measured, docs/geometry.md).
BEAM_ALPHA_EXPONENT = 3.5
#: Power of a beam wider in lines than :data:`REFERENCE_CELL_LINES` that gives back a long pulse's reduction in
#: :func:`beam_alpha_factor` (measured: a 3 MHz bending pair whose cell reads 3.5 lines needs at least 1.7).
BEAM_WIDTH_EXPONENT = 2.0


def beam_alpha_factor(line_spacing_mm: float, rf_period_mm: float | None = None,
                      cell_lines: float | None = None) -> float:
    """Factor on the default alpha of the physical solve of a beam frame whose lines are ``line_spacing_mm`` apart
    at the middle sample: ``max(1, s_eff / 0.3 mm)**3.5``, ``s_eff = s min(1, (0.14 mm / P) max(1, c / 2.8)**2)``
    with ``P = rf_period_mm`` the frame's axial RF period (:func:`femreg.speckle.rf_period`) and ``c =
    cell_lines`` its lateral speckle cell in lines (:func:`lateral_cell_lines`); None for either: that term is 1,
    so ``beam_alpha_factor(s) = max(1, s / 0.3)**3.5``.  1 for lines at most 0.3 mm apart.

    Coarse fans over-estimate the across-ray strain (the speckle of a beam-aligned PSF several lines wide does not
    follow a uniform physical strain off axis, and the images prefer the biased field: see docs/geometry.md); the
    weakly determined across-ray stretch needs the stronger regulariser.  The power 3.5
    (:data:`BEAM_ALPHA_EXPONENT`) is the measured balance on the paper probe (5.5 MHz, 3 lines per beam): 3
    leaves 2.2-2.5 % error at 2 % compression and 0.6 degrees per line, 4 puts the stiff inclusion 1.2 x the linear
    array's error.  A pulse longer than the paper probe's biases less and is smoothed more by the same weight, so
    the spacing is counted in its RF periods (benchmarks/convex_alpha_beam.py: 3 MHz, 1.08 mm lines, 3 lines per
    beam, stiff inclusion 12.6 -> 9.4 % total strain error, uniform 1 % / 2 % compression 1.3 / 0.9 -> 1.8 / 2.5
    %); a beam wider in lines than the calibration's gives that back as the square of its width (uniform strain is
    biased more: 3 MHz, 4.5 lines per beam, 1 % compression 0.7 % at the spacing's factor, 6.1 % at the period's
    alone; a bending pair whose cell reads 3.5 lines 4.87 % at the spacing's factor, 5.96 % with the width's first
    power, 4.85 % with its square).  A shorter
    pulse or a narrower beam keeps the spacing's factor: with the paper probe's pulse, 2 lines per beam bias
    uniform compression nearly as much as 3 (6.4 against 8.1 % at factor 1, 1.08 mm lines).  A user's alpha is
    used as given."""
    s = float(line_spacing_mm)
    if rf_period_mm is not None and np.isfinite(rf_period_mm) and rf_period_mm > REFERENCE_RF_PERIOD:
        wide = float(cell_lines) / REFERENCE_CELL_LINES if cell_lines is not None and np.isfinite(cell_lines) else 1.0
        s *= min(1.0, REFERENCE_RF_PERIOD / float(rf_period_mm) * max(1.0, wide) ** BEAM_WIDTH_EXPONENT)
    return max(1.0, s / REFERENCE_LINE_SPACING) ** BEAM_ALPHA_EXPONENT


def lateral_cell_lines(frame) -> float:
    """Lateral speckle cell of an RF frame (n_samples, n_lines) in lines: the full width at half maximum of the
    envelope's autocorrelation across lines, each row divided by its RMS and less its mean (a level that changes
    with depth alone is the same in every line), interpolated linearly between lags (femreg.speckle's cell counts
    whole lags: 2, 4 or 6 lines on fans whose beam spans 2-4.5 lines).  NaN when it cannot be read (under 4 lines,
    no echo, or no half maximum within 12 lags).  Simulated fans (forward.beam) read 0.9 x their lines per beam
    (2 / 3 / 4.5: 1.8 / 2.7-2.9 / 3.8-4.2)."""
    from .speckle import envelope

    img = np.asarray(frame, float)
    if img.ndim != 2 or img.shape[1] < 4 or not np.all(np.isfinite(img)):
        return float("nan")
    env = envelope(img)
    rms = np.sqrt(np.mean(env * env, axis=1, keepdims=True))
    e = np.divide(env, rms, out=np.zeros_like(env), where=rms > 0)
    e -= e.mean(axis=1, keepdims=True)
    n, a0 = e.shape[1], float(np.vdot(e, e))
    if a0 <= 0:
        return float("nan")
    ac = [1.0]
    for k in range(1, min(12, n - 1)):
        ac.append(float(np.vdot(e[:, :-k], e[:, k:])) / a0 * n / (n - k))      # unbiased: fewer pairs per lag
        if ac[-1] < 0.5:
            return 2.0 * (k - 1 + (ac[-2] - 0.5) / (ac[-2] - ac[-1]))
    return float("nan")


def default_beam_alpha_factor(frame, dr: float, ds: float) -> float:
    """:func:`beam_alpha_factor` of a beam frame (n_samples, n_rays) in sample space (range step ``dr`` mm, line
    spacing ``ds`` mm at the middle sample), its RF period and (for a pulse longer than the paper probe's) its
    lateral speckle cell measured on the frame."""
    from .speckle import rf_period

    period = rf_period(frame, (dr, ds))
    cell = lateral_cell_lines(frame) if period > REFERENCE_RF_PERIOD else None
    return beam_alpha_factor(ds, period, cell)


def _image_term(ref, mov, mesh, geometry, dr, r0, normalize=True):
    """``(I1, I2, term)``: the splines of a beam pair on their (range, angle) grids and the image term of eq:IR
    over the samples inside the physical ``mesh`` (:class:`BeamSSDTerm`)."""
    if normalize:
        ref, mov, _ = normalize_pair(ref, mov)
    sp_idx = (dr, geometry.pitch_rad)
    I1, I2 = SplineImage(ref, sp_idx, (r0, 0.0)), SplineImage(mov, sp_idx, (r0, 0.0))
    quad = BeamQuadrature(mesh, ref.shape, sp_idx, (r0, 0.0), geometry, locator=PointLocator(mesh))
    if quad.n_pixels == 0:
        raise InputError("no sample lies inside the mesh")
    return I1, I2, BeamSSDTerm(quad, I1, I2)


def beam_image_term(reference_image, moving_image, mesh, register_kwargs):
    """The :class:`femreg.autoalpha.ImageTerm` of a convex / sector pair on the physical ``mesh`` (the
    ``image_term`` of :func:`femreg.autoalpha.choose_alpha` for beam frames), built as :func:`register_beam`
    builds its image term; ``register_kwargs`` hold ``geometry``, ``spacing``, ``origin`` (and ``normalize``)."""
    from .autoalpha import ImageTerm
    from .image import validate_image

    geometry = as_geometry(register_kwargs["geometry"])
    dr, r0 = beam_spacing(register_kwargs["spacing"], geometry, register_kwargs.get("origin", (0.0, 0.0)))
    ref = validate_image(reference_image, "reference image")
    _, _, term = _image_term(ref, validate_image(moving_image, "moving image"), mesh, geometry, dr, r0,
                             register_kwargs.get("normalize", True))
    idx = term.quad.index

    def on_samples(values):
        out = np.zeros(ref.size)
        out[idx] = values
        return out.reshape(ref.shape)

    return ImageTerm(data=term, n_samples=term.quad.n_pixels, residual_image=lambda u: on_samples(term.residual(u)),
                     gradients=(on_samples(term._gx), on_samples(term._gy)))


def _beam_orientation_error(exc, ref, geometry, dr, ds, rho_c):
    """The sample-space check's refusal in the probe's terms: its lateral spacing is the rays' distance
    ``rho_c dtheta`` at the middle sample, set by ``angle_pitch_deg`` (and the radius), not a line pitch to swap
    with the range step."""
    from .orientation import MIN_LATERAL_CELL_PERIODS, diagnose, transposed_message

    if getattr(exc, "problem", "") == "transposed":
        # the lateral value checked is the rays' distance at the middle sample, not one the user gave or can
        # keep: a convex / sector frame's spacing is the range step alone
        rep = getattr(exc, "report", None)
        return exc if rep is None else OrientationError(transposed_message(rep, range_step=True),
                                                        problem="transposed", report=rep)
    if getattr(exc, "problem", "") not in ("swapped", "spacing"):
        return exc
    rep = diagnose(ref, (dr, ds))
    a = float(geometry.angle_pitch_deg)
    what = (f"the rays are {ds:.4g} mm apart at the middle sample (angle pitch {a:g} deg at {rho_c:.4g} mm from the "
            f"apex; range step {dr:g} mm)")
    k = 180.0 / np.pi            # an angle pitch given in radians: the rays k x further apart
    if rep.cell_periods < MIN_LATERAL_CELL_PERIODS and rep.cell_periods * k >= MIN_LATERAL_CELL_PERIODS:
        hint = (f"the angle pitch looks given in radians: --angle-pitch takes degrees, {a:g} rad = {a * k:.4g} deg "
                "(" + pass_as(f"angle_pitch_deg={a * k:.4g}; CLI: --angle-pitch {a * k:.4g}",
                              f"--angle-pitch {a * k:.4g}")
                + ")")
    else:
        hint = ("check --angle-pitch (degrees between neighbouring rays), --radius (mm from the apex to the face) "
                "and the range step (the axial spacing, mm)")
    return OrientationError(f"{geometry.kind} frames: {what}; lateral speckle {rep.lateral_cell_mm:.3g} mm, "
                            f"{rep.cell_periods:.2f} of one axial RF period ({rep.period_mm:.3g} mm): narrower than "
                            f"the diffraction limit allows; {hint}, or {override()}", problem="spacing")


def register_beam(reference_image, moving_image, *, geometry, spacing, origin=(0.0, 0.0), register,
                  regularizer="momentum-stress", alpha=None, maxiter=20, tol=1e-3, linear_solver="auto",
                  normalize=True, callback=None, strain_tol=None, refine=None, **kw) -> BeamResult:
    """``femreg.register`` for a beam frame (module docstring): the sample-space registration as the initial
    guess, then Gauss-Newton of eq:objf on the physical annular-sector mesh.  ``register`` is
    :func:`femreg.register` (the sample-space stage, never refined); ``kw`` its other options (offset and
    ``alpha="auto"`` are not supported here; a ``mesh`` is a physical quad mesh, e.g. a tracking run's frame-0
    mesh moved with the tissue, whose nodes are mapped to (r, s) for the sample-space stage; with it a nodal
    ``initial`` (a physical displacement of its nodes) starts the physical solve directly, without the
    sample-space stage); ``refine`` refines the physical mesh (module docstring)."""
    from .gnsolve import solve
    from .image import validate_image
    from .refine import (Refinement, as_refinement, pass_regularizer, pass_solve_kw, refine_name, refine_passes,
                         transfer, with_logical_grid, with_refinement)
    from .repair import check_period, check_result
    from .solver import GN_STRAIN_TOL, GN_STRAIN_TOL_TIGHT
    from .strategy import (component_tol, effective_regularizer_options, fresh_regularizer, lambda_bar_follows_data,
                           lambda_bar_stage)

    t_all = time.perf_counter()
    geometry = as_geometry(geometry)
    if isinstance(geometry, Swept):
        raise InputError("a femreg.Swept geometry is a swept probe's: it needs volumes (n_samples, n_lines, "
                         "n_frames), not a frame")
    if kw.get("offset") is not None:
        raise InputError(f"offset= is not supported with a {geometry.kind} geometry")
    roi = kw.get("roi")
    if roi is not None and not isinstance(roi, str) and kw.get("mesh") is None:
        # the sample-space stage would read it as (range, arc length at the middle sample), not as x, y
        raise InputError(pass_as(f"roi {roi!r} is a Cartesian rectangle: with a {geometry.kind} geometry give depth="
                                 "(d0, d1), a range along the rays in mm",
                                 f"--roi is a Cartesian rectangle: with --geometry {geometry.kind} give --depth D0 D1 "
                                 "(a range along the rays, mm) instead"))
    if isinstance(alpha, str):
        raise InputError(pass_as(f"alpha='auto' is not supported with a {geometry.kind} geometry",
                                 f"--alpha auto is not supported with --geometry {geometry.kind}"))
    ref = validate_image(reference_image, "reference image")
    mov = validate_image(moving_image, "moving image")
    if ref.shape != mov.shape:
        raise InputError(f"image shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    dr, r0 = beam_spacing(spacing, geometry, origin)
    shape = ref.shape
    rho_c, (_, ds), (_, s0) = sample_space(geometry, shape, dr, r0)
    lat = _Lattice(geometry, rho_c)
    start = None
    if kw.get("mesh") is not None:
        # a physical mesh (a tracking run's frame-0 mesh, possibly moved with the tissue): its nodes in (r, s)
        mesh_p = as_quad_mesh(kw["mesh"])
        kw["mesh"] = MeshQuad1(lat.to_logical(mesh_p.p.T), mesh_p.t)
        if not isinstance(kw.get("initial"), (str, type(None))) and not callable(kw["initial"]):
            # a nodal start (the previous increment of a track): the physical solve starts from it directly.
            # Through the sample-space stage it failed spuriously: that start minimised the physical objective,
            # and the sample-space one, judged never worse than its start, rejected it (docs/geometry.md)
            start = nodal_values(kw["initial"], mesh_p)
    # -- initial guess: the linear pipeline in sample space (r, s = rho_c theta) ------------------------------
    t = time.perf_counter()
    if start is None:
        try:
            inner = register(ref, mov, spacing=(dr, ds), origin=(r0, s0), regularizer=regularizer, alpha=alpha,
                             maxiter=maxiter, tol=tol, linear_solver=linear_solver, normalize=normalize,
                             strain_tol=strain_tol, refine=None, **kw)
        except OrientationError as exc:
            raise _beam_orientation_error(exc, ref, geometry, dr, ds, rho_c) from None
        mesh_s, u0 = inner.mesh, to_physical_displacement(inner.mesh, inner.u, geometry, rho_c)
    else:
        inner, mesh_s, u0 = None, kw["mesh"], start
    t_inner = time.perf_counter() - t
    # the physical mesh carries its (r, s) lattice: refinement splits there (femreg.refine.LogicalGrid)
    mesh = with_logical_grid(mesh_s, lat.angle, lat.to_physical, lat.to_logical)
    # -- Gauss-Newton on the physical mesh --------------------------------------------------------------------
    t = time.perf_counter()
    strategy = kw.get("strategy", "auto")
    opts = effective_regularizer_options(strategy, regularizer, kw.get("regularizer_options"))
    user_reg = fresh_regularizer(regularizer, alpha, opts)
    if alpha is None and isinstance(regularizer, str):
        user_reg = fresh_regularizer(regularizer, user_reg.alpha * default_beam_alpha_factor(ref, dr, ds), opts)
    sp_idx = (dr, geometry.pitch_rad)
    I1, I2, term = _image_term(ref, mov, mesh, geometry, dr, r0, normalize)
    locator = term.quad.locator
    st = float(strain_tol) if strain_tol is not None else (
        GN_STRAIN_TOL_TIGHT if getattr(user_reg, "quadratic", False) else GN_STRAIN_TOL)
    solve_kw = dict(maxiter=maxiter, tol=component_tol(tol, u0) if strategy == "auto" else tol,
                    linear_solver=linear_solver, callback=callback, mask_outside=strategy == "auto",
                    strain_tol=st if (strategy == "auto" and st > 0) else None)
    def physical_solve(u):          # Gauss-Newton on the physical mesh from the nodal displacement u
        return solve(I1, I2, mesh, shape, sp_idx, (r0, 0.0), lambda: copy.copy(user_reg), u, locator=locator,
                     term=term, **solve_kw)
    sol = physical_solve(u0)
    # R_P_sigma's lambda_bar from the physical field's strain ratio, as femreg.register; the refinement marks on
    # the solve before it
    notes = []
    marked, sol = lambda_bar_stage(sol, user_reg, notes, physical_solve,
                                   follows=lambda_bar_follows_data(strategy, regularizer, kw.get("regularizer_options"),
                                                                   maxiter) and shape[0] > 1)
    timings = dict(sample_space=t_inner, gauss_newton=time.perf_counter() - t)
    period = check_period(ref, (dr, ds)) if shape[0] > 1 else None

    def checked(s, start):
        return check_result(_judged_on_objf(s, start), start, np.zeros(s.mesh.p.shape[1], int), shape, (dr, dr),
                            period, None)
    # -- adaptive refinement (femreg.refine) on the (r, s) lattice, the physical solve on each refined mesh -----
    # "auto" here: the two-pass refinement measured on these frames (benchmarks/convex_refine.py)
    opts = as_refinement(Refinement() if refine_name(refine) == "auto" else refine)
    refined = None
    if opts is not None and int(maxiter) > 0:
        t = time.perf_counter()

        def solve_on(m, u_start, shear_traction=None, normal_traction=None, alpha_factor=1.0, full=False,
                     steps=None, hourglass=None):
            def factory():
                return pass_regularizer(copy.copy(user_reg), mesh, m, alpha_factor, hourglass, shear_traction,
                                        normal_traction)
            loc = PointLocator(m)
            tm = BeamSSDTerm(BeamQuadrature(m, shape, sp_idx, (r0, 0.0), geometry, locator=loc), I1, I2)
            kw_m = pass_solve_kw(opts, solve_kw, maxiter, full, steps)
            return solve(I1, I2, m, shape, sp_idx, (r0, 0.0), factory, u_start, locator=loc, term=tm, **kw_m)

        refined, record = refine_passes(sol if marked is None else marked, opts, solve_on, (dr, ds), (r0, s0),
                                        start=None if marked is None else sol)
        timings["refine"] = time.perf_counter() - t
        notes.append(record.summary())
    if refined is not None and refined.mesh is not mesh:
        check = checked(refined, transfer(u0, mesh, refined.mesh))
        if check.success:
            sol = refined
        else:
            # as femreg.register: a refined result judged on smaller elements that fails its check is dropped
            why = "; ".join(n for n in check.notes if not n.startswith("the pair is strongly decorrelated"))
            notes.append(f"refinement dropped (the refined result failed its check: {why})")
            check = checked(sol, u0)
    else:
        check = checked(sol, u0)
    if refined is not None:
        sol.refinement = record
    timings["total"] = time.perf_counter() - t_all
    notes += list(check.notes)
    if inner is not None and not inner.success:
        notes.append("sample-space start: " + inner.message)
    success = check.success and (inner is None or inner.success)
    message = "; ".join([sol.gn.message] + notes) if notes else sol.gn.message
    res = BeamResult(sol.mesh, check.u, shape=shape, spacing=(dr, geometry.angle_pitch_deg), origin=(r0, 0.0),
                      regularizer=sol.reg.name, alpha=user_reg.alpha, success=success, status=sol.gn.status,
                      message=message if success else "FAILED: " + message, nit=sol.gn.nit,
                      energy_history=sol.gn.energy_history, ncc_before=check.ncc_before,
                      ncc_after=check.ncc_after, timings=timings, solver_result=sol.gn, locator=sol.locator,
                      quality=check.quality, strategy=strategy, alpha_effective=sol.reg.alpha,
                      hop_gain=check.hop_gain, geometry=geometry, sample_space=inner,
                      lambda_bar=getattr(sol.reg, "lambda_bar", None))
    if inner is not None and inner.excluded:
        # what the sample-space stage left out (femreg.echo), in the probe's own terms: ranges along the rays and
        # ray angles, not the (r, s) rectangle it was cut in
        cut = getattr(inner, "echo_region", None)
        res.excluded = inner.excluded if cut is None else beam_excluded(cut, rho_c)
        res.message = f"{res.message}; {res.excluded}"
    return with_refinement(res, sol)


def beam_excluded(region, rho_c: float, *, rows_only: bool = False) -> str | None:
    """What a sample-space crop leaves out, said in a beam frame's terms: ``region`` the
    :class:`femreg.echo.EchoRegion` (in range r, arc s at ``rho_c`` mm) it was cut to.  From its data: rows cut at
    the top / bottom read ``range before / beyond R mm (along the rays)``, lines cut at a side (arc mm) ray angles
    in degrees (``rays at A to B deg``), a given box its range and rays; ``rows_only``: the rows' cuts alone (a
    crop that keeps every ray).  None when nothing is said; a region without cut data (a fan's fill) says its own
    ``excluded``."""
    def deg(v):
        return np.rad2deg(float(v) / rho_c) + 0.0

    def rays(c):
        return f"rays at {deg(c.lo):.1f} to {deg(c.hi):.1f} deg"

    if region.given is not None:
        x0, x1, y0, y1 = region.roi_mm
        return (f"outside the given {region.given}: range {x0:.1f}-{x1:.1f} mm, rays at {deg(y0):.1f} to "
                f"{deg(y1):.1f} deg excluded")
    if not region.cuts and not rows_only:
        return region.excluded          # no cut data: a fan's fill says its own
    parts = []
    for c in region.row_cuts if rows_only else region.cuts:
        if c.axis == "depth" and c.side in ("above", "below"):
            where = "before" if c.side == "above" else "beyond"
            parts.append(f"range {where} {c.edge:.1f} mm (along the rays) {c.why}")
        elif c.axis == "depth":         # saturated ranges: cut (no side), or kept inside the region
            parts.append(f"{'saturated ranges at' if c.side == 'kept' else 'range'} {c.span} (along the rays) {c.why}")
        else:
            parts.append(f"{rays(c)} ({c.side}) {c.why}" if c.side else f"{rays(c)} {c.why}")
    return "; ".join(parts) or None


def _judged_on_objf(sol, u0):
    """``sol`` with its start ``u0`` and the psi the check's never-worse rule compares with: the start minimised
    the sample-space objective, not this one, so the physical solve may trade a little of the image term for the
    physical regulariser; "never worse than the start" is judged on eq:objf here (psi of the result when eq:objf
    fell)."""
    psi0 = sol.psi_start if sol.start is u0 else sol.data.energy(u0)
    psi1 = sol.data.energy(sol.u)
    if psi1 > psi0 and psi1 + sol.reg.energy(sol.u) <= psi0 + sol.reg.energy(u0):
        psi0 = psi1
    return dataclasses.replace(sol, start=u0, psi_start=psi0)
