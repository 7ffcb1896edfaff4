"""Coarse-to-fine initial guess of the default ``strategy="auto"`` of :func:`femreg.register`, with defaults
measured from the images.

Gauss-Newton on an RF image is a local method: it converges to the correlation peak within about a quarter of
the RF period of its start, and from further away to a neighbouring peak one period off ("peak hopping").  The
paper's NCC block matching (fixed 5 x 9 mm windows, +-1.5 mm search) gives such a start only inside its protocol.
Here the start comes from a pyramid, as in optical flow (Lucas-Kanade pyramids), elastix and GLUE:

1. :func:`speckle_statistics` -- RF period and speckle cell size (axial, lateral) from the spectrum and the
   envelope autocorrelation; :func:`default_settings` derives element size, decimation, windows and search
   ranges from them and from the image extent (instead of the paper's millimetres).
2. Top level, envelopes low-passed and decimated to ~3 samples per speckle cell: a global search over
   translations up to 10 % of the image depth (axial) and width (lateral) and axial strains from -12 % to +6 %
   (:func:`global_search`), then NCC block matching of speckle-sized windows on the envelope of the moving image
   warped by that field, searching only around it (:func:`local_search`).
3. Gauss-Newton on the envelopes with a mesh twice as coarse as the final one, from that field (the envelope has
   no carrier, so its basin is a speckle cell wide, not a quarter period).
4. The final level (RF, fine mesh) is solved by :func:`femreg.register` from the envelope-level field; the
   envelope-level field is also the reference the repair stage (:mod:`femreg.repair`) checks the RF result
   against.

Every level warps the moving image by the whole field of the level above (not only its affine part).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

from .blockmatch import block_match
from .data_term import SSDTerm
from .image import SplineImage
from .mesh import roi_mesh
from .pixels import PixelQuadrature, PointLocator
from .scaling import effective_alpha
from .solver import Objective, gauss_newton

__all__ = ["SpeckleStats", "PyramidSettings", "speckle_statistics", "default_settings", "envelope",
           "global_search", "local_search", "field_at", "pyramid_initial_guess", "PyramidGuess"]

#: Largest motion the top level searches, as a fraction of the image extent (axial, lateral).
SEARCH_FRACTION = (0.10, 0.10)
#: Axial strains tried by the global search (fraction; negative = compression).
GLOBAL_STRAINS = tuple(np.round(np.arange(-0.12, 0.0601, 0.01), 3))


@dataclass
class SpeckleStats:
    """What the image itself says about its scale (mm): ``period`` = axial RF period (1 / spectral centroid),
    ``cell`` = (axial, lateral) full width at half maximum of the envelope autocorrelation."""

    period: float
    cell: np.ndarray


@dataclass
class PyramidSettings:
    """Defaults derived from the image: ``element_size`` (2,) mm of the final mesh, ``decimation`` (axial factor
    of the envelope level), ``window`` / ``search`` (2,) mm of the local block matching."""

    element_size: np.ndarray
    decimation: int
    window: np.ndarray
    search: np.ndarray


def envelope(image) -> np.ndarray:
    """Envelope |analytic signal| along the axial direction (scipy.signal.hilbert)."""
    return np.abs(signal.hilbert(np.asarray(image, float), axis=0))


def speckle_statistics(image, spacing) -> SpeckleStats:
    """RF period from the axial power spectrum's centroid; speckle cell from the envelope autocorrelation
    (FFT, zero-padded, averaged over lines / rows), both in mm."""
    img = np.asarray(image, float)
    dx, dy = float(spacing[0]), float(spacing[1])
    P = np.mean(np.abs(np.fft.rfft(img - img.mean(axis=0), axis=0)) ** 2, axis=1)
    f = np.fft.rfftfreq(img.shape[0], dx)
    fc = float(np.sum(f * P) / np.sum(P)) if np.sum(P) > 0 else 0.0
    period = 1.0 / fc if fc > 0 else float(img.shape[0] * dx)
    e = envelope(img)
    e = e - e.mean()
    cell = []
    for ax, d in ((0, dx), (1, dy)):
        m = e.shape[ax]
        F = np.fft.rfft(e, n=2 * m, axis=ax)
        ac = np.fft.irfft(np.abs(F) ** 2, axis=ax)
        ac = (ac[:m] if ax == 0 else ac[:, :m]).mean(axis=1 - ax)
        ac = ac / ac[0] if ac[0] > 0 else ac
        below = np.flatnonzero(ac < 0.5)
        k = below[0] if below.size else m
        cell.append(2.0 * k * d)
    return SpeckleStats(period=period, cell=np.array(cell))


def default_settings(shape, spacing, stats: SpeckleStats, element_size=None) -> PyramidSettings:
    """Defaults from the image (all mm).

    * Element size: square, ``max(6 axial cells, 1.1 lateral cells)`` -- about 2 mm for the paper's probe
      (cell 0.35 x 1.8 mm), 3.3 mm at 3 MHz, 0.9 mm at 12 MHz -- at most 1/12 of the smaller image extent, at
      least 2 lines and 8 samples.  (On tissue the envelope autocorrelation also holds structure: the
      cap of 1/12 of the extent keeps the mesh fine there, 2.1 mm on the 40 x 25.6 mm in vivo frames.)
    * Envelope decimation: ~3 samples per axial speckle cell.
    * Local block matching: windows of 8 x 3 cells (at least 1/12 x 1/8 of the image), search 3 x 2 cells.
    """
    spacing = np.asarray(spacing, float)
    extent = np.asarray(shape, float) * spacing
    if element_size is None:
        h = max(6.0 * stats.cell[0], 1.1 * stats.cell[1])
        h = min(h, extent.min() / 12.0)
        h = np.maximum(np.array([h, h]), np.array([8 * spacing[0], 2 * spacing[1]]))
    else:
        h = np.broadcast_to(np.asarray(element_size, float), (2,)).copy()
    q = int(max(1, np.floor(stats.cell[0] / (3.0 * spacing[0]))))
    window = np.maximum([8.0 * stats.cell[0], 3.0 * stats.cell[1]], extent / np.array([12.0, 8.0]))
    window = np.minimum(window, extent / 2.0)
    search = np.array([3.0 * stats.cell[0], 2.0 * stats.cell[1]])
    return PyramidSettings(element_size=h, decimation=q, window=window, search=search)


def _decimated_envelopes(ref, mov, q):
    """Low-passed (Gaussian, sigma q/2 samples axially) and decimated envelopes, zero mean, unit RMS (ref)."""
    out = []
    for img in (ref, mov):
        e = envelope(img)
        if q > 1:
            e = ndimage.gaussian_filter1d(e, 0.5 * q, axis=0)[::q]
        out.append(e)
    m = out[0].mean()
    s = out[0].std() or 1.0
    return (out[0] - m) / s, (out[1] - m) / s


def _warp(image, spacing, origin, field_grid):
    """image(x + u(x)) on its own pixel grid, u given per pixel (n_a, n_l, 2) mm; cubic, zero outside."""
    ii, jj = np.meshgrid(np.arange(image.shape[0]), np.arange(image.shape[1]), indexing="ij")
    return ndimage.map_coordinates(image, [ii + field_grid[..., 0] / spacing[0], jj + field_grid[..., 1] / spacing[1]],
                                   order=3, mode="constant", cval=0.0)


def _pixel_points(shape, spacing, origin):
    x = origin[0] + spacing[0] * np.arange(shape[0])
    y = origin[1] + spacing[1] * np.arange(shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel()])


def global_search(ref_env, mov_env, spacing, origin, *, strains=GLOBAL_STRAINS, fraction=SEARCH_FRACTION):
    """Best (shift, axial strain) over translations up to ``fraction`` of the extent and the given axial strains.

    For each strain e the moving envelope is pre-warped by u_x = e (x - x_mid) and one window covering the
    central part of the reference is matched by NCC over every shift.  Returns ``(coef, ncc)``: the affine field
    coefficients (3, 2) as in :meth:`BlockMatchResult.affine_fit` and the peak NCC."""
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    shape = np.asarray(ref_env.shape)
    extent = shape * spacing
    search = np.asarray(fraction) * extent
    window = np.maximum(extent - 2.0 * search, 2.0 * spacing)
    xm = origin[0] + 0.5 * (shape[0] - 1) * spacing[0]
    x = origin[0] + spacing[0] * np.arange(shape[0])
    best = (None, -np.inf)
    for e in strains:
        ux = e * (x - xm)
        grid = np.zeros(tuple(shape) + (2,))
        grid[..., 0] = ux[:, None]
        warped = _warp(mov_env, spacing, origin, grid) if e else mov_env
        bm = block_match(ref_env, warped, spacing, origin, window=tuple(window), overlap=(0.0, 0.0),
                         search=tuple(search), median_size=1, subsample=True, compand_strain=None)
        c = float(np.max(bm.ncc))
        if c > best[1]:
            k = np.unravel_index(np.argmax(bm.ncc), bm.ncc.shape)
            s = bm.raw[k]
            coef = np.zeros((3, 2))
            coef[0] = s
            coef[0, 0] += -e * xm
            coef[1, 0] = e
            best = (coef, c)
    return best


def _affine(coef, pts):
    return np.column_stack([coef[0, c] + coef[1, c] * pts[:, 0] + coef[2, c] * pts[:, 1] for c in range(2)])


def local_search(ref_env, mov_env, spacing, origin, prior, settings: PyramidSettings):
    """Block matching of ``ref_env`` against ``mov_env`` warped by ``prior`` (callable points -> (n, 2) mm),
    searching ``settings.search`` around it; returns callable total field (prior + filtered residual)."""
    spacing = np.asarray(spacing, float)
    pts = _pixel_points(ref_env.shape, spacing, origin)
    grid = prior(pts).reshape(ref_env.shape + (2,))
    warped = _warp(mov_env, spacing, origin, grid)
    bm = block_match(ref_env, warped, spacing, origin, window=tuple(settings.window), overlap=(0.5, 0.5),
                     search=tuple(settings.search), median_size=3, subsample=True, compand_strain=None)

    def total(p):
        return prior(p) + bm(p)
    return total, bm


def field_at(mesh, u, points, locator: PointLocator | None = None) -> np.ndarray:
    """Nodal field ``u`` (2 n_nodes,) of ``mesh`` at ``points`` (n, 2) mm -> (n, 2) mm; points outside the
    mesh take the value at the nearest point of the mesh's bounding box (exact for the structured ROI meshes)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
    q = np.clip(pts, lo, hi)
    loc = (locator or PointLocator(mesh)).locate(q)
    out = np.zeros((len(q), 2))
    out[loc.inside, 0] = np.sum(loc.N * u[0::2][loc.nodes], axis=1)
    out[loc.inside, 1] = np.sum(loc.N * u[1::2][loc.nodes], axis=1)
    if not loc.inside.all():             # clamped points on a non-convex user mesh: nearest node
        from scipy.spatial import cKDTree

        _, k = cKDTree(mesh.p.T).query(q[~loc.inside])
        out[~loc.inside] = np.column_stack([u[0::2][k], u[1::2][k]])
    return out


@dataclass
class PyramidGuess:
    """Output of :func:`pyramid_initial_guess`: the envelope-level field on its coarse mesh (``mesh``, ``u``),
    the speckle statistics and settings, the global search's NCC and the block matching of the top level."""

    mesh: object
    u: np.ndarray
    stats: SpeckleStats
    settings: PyramidSettings
    global_ncc: float
    blockmatch: object
    timings: dict

    def __call__(self, points) -> np.ndarray:
        return field_at(self.mesh, self.u, points)


def pyramid_initial_guess(ref, mov, spacing, origin, *, regularizer_factory, alpha, stats: SpeckleStats,
                          settings: PyramidSettings, margin=None, maxiter: int = 20, tol: float = 1e-3,
                          linear_solver: str = "splu") -> PyramidGuess:
    """Steps 2-3 of the module docstring on normalised RF images ``ref``, ``mov`` (n_a, n_l).

    ``regularizer_factory()`` returns a fresh regulariser (user alpha set); its weight on the coarse mesh is
    scaled by :func:`femreg.scaling.effective_alpha`."""
    import time

    timings = {}
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    t = time.perf_counter()
    q = settings.decimation
    er, em = _decimated_envelopes(ref, mov, q)
    sp_c = np.array([q * spacing[0], spacing[1]])
    timings["envelopes"] = time.perf_counter() - t

    t = time.perf_counter()
    coef, gncc = global_search(er, em, sp_c, origin)
    timings["global_search"] = time.perf_counter() - t

    t = time.perf_counter()
    field, bm = local_search(er, em, sp_c, origin, lambda p: _affine(coef, p), settings)
    timings["local_search"] = time.perf_counter() - t

    t = time.perf_counter()
    mesh = roi_mesh(er.shape, sp_c, origin, element_size=tuple(2.0 * settings.element_size), margin=margin)
    quad = PixelQuadrature(mesh, er.shape, sp_c, origin)
    data = SSDTerm(quad, SplineImage(er, sp_c, origin), SplineImage(em, sp_c, origin))
    reg = regularizer_factory()
    reg.alpha = effective_alpha(reg.alpha, mesh)
    reg.setup(mesh)
    pts = mesh.p.T
    v = field(pts)
    u0 = np.empty(2 * len(pts))
    u0[0::2], u0[1::2] = v[:, 0], v[:, 1]
    gn = gauss_newton(Objective(data, reg), u0, maxiter=maxiter, tol=tol, linear_solver=linear_solver)
    u = gn.x if data.energy(gn.x) <= data.energy(u0) else u0
    timings["envelope_gauss_newton"] = time.perf_counter() - t
    return PyramidGuess(mesh=mesh, u=u, stats=stats, settings=settings, global_ncc=gncc, blockmatch=bm,
                        timings=timings)
