"""The result of a registration: :class:`RegistrationResult` (a nodal displacement on a quad mesh, sampled on
points and on the reference pixel grid through :mod:`femreg.sampling`, saved and loaded through the ``.npz``
contract of :mod:`femreg.io.results`), and the conversions of a displacement given as a callable, a nodal vector,
a result or a block-matching field (:func:`displacement_at`, :func:`nodal_values`).
"""
from __future__ import annotations

import numpy as np

from .blockmatch import BlockMatchResult
from .errors import InputError
from .fields import (DEFAULT_RECOVERY, adaptive_strains, adaptive_weight, check_strain_mode, recovered_strains,
                     strain_roughness)
from .io.results import read_result, save_result
from .pixels import PointLocator
from .result_base import ResultRecord
from .sampling import PixelGrid, sample_grid, sample_points

__all__ = ["RegistrationResult", "load_result", "displacement_at", "nodal_values"]


class RegistrationResult(ResultRecord):
    r"""A registered displacement field on a quad mesh.

    Attributes
    ----------
    mesh : skfem.MeshQuad1
        mm; ``mesh.p[0]`` axial x, ``mesh.p[1]`` lateral y.
    u : (2 n_nodes,) float, mm
        Nodal displacement, interleaved (u[0::2] = ux, u[1::2] = uy), scikit-fem DOF order.
    success, status, message, nit, energy_history
        From the Gauss-Newton solver (:class:`femreg.solver.GaussNewtonResult`).
    regularizer : str
        Name of the regulariser; ``alpha`` its weight (for the normalised images).
    ncc_before, ncc_after : float
        NCC of reference vs moving over the mesh pixels, at u = 0 and at the result: a quality measure.
    shape, spacing, origin
        Reference pixel grid.
    timings : dict
        Seconds per stage.
    blockmatch : BlockMatchResult or None
        The initial-guess field, if block matching was used.
    quality : (n_elements,) float or None
        Per-element NCC of reference and warped moving image at the result (NaN where an element holds fewer
        than 4 pixels): low values mark decorrelation, peak hopping or a failed region.
    strategy : str
        "auto" or "paper" (see :func:`register`); ``alpha_effective`` the weight used on this mesh
        (:mod:`femreg.scaling`).
    hop_gain : (n_elements,) float or None
        Peak-hopping map of :func:`register`'s check (:func:`femreg.repair.hop_gain`, not saved): per element, how
        much better the envelope matches one RF period off than at u (Fisher z); above
        :data:`femreg.repair.HOP_GAIN` the element sits on a neighbouring correlation peak.
    excluded : str or None
        What of the frames was left out of the mesh and the image term, and why (:mod:`femreg.echo`: no usable
        echo, saturation, or the user's ``roi`` / ``depth``); None when the whole frames were registered.
    roi : (x0, x1, y0, y1) mm or None
        The rectangle registered (the mesh covers it, less the margin at the image edges); None: the whole frames.
    lambda_bar : float or None
        :math:`\bar\lambda` (eq:meq) of the momentum regulariser that solved: R_P_sigma's 2 (plane stress) or,
        where the data read plane strain, 9 (:func:`femreg.strategy.data_lambda_bar`); None for the other
        regularisers.
    started_afresh : bool
        True where a track's increment started from the strategy's own start rather than the previous increment,
        the frames matching better with no motion (:func:`femreg.initial.previous_or_fresh`; the message says so
        too): a track does not retry it.  Saved with the result.
    """

    #: Names of the columns of :meth:`strain` and :meth:`displacement` (a volume's result has six and three:
    #: :class:`femreg.volume_result.VolumeResult`); consumers index strains by these names.
    strain_components = ("exx", "eyy", "exy")
    displacement_components = ("ux", "uy")
    ndim = 2

    def __init__(self, mesh, u, *, shape, spacing, origin, regularizer="", alpha=float("nan"), success=False,
                 status=-1, message="", nit=0, energy_history=(), ncc_before=float("nan"),
                 ncc_after=float("nan"), timings=None, blockmatch=None, solver_result=None, grid=None,
                 locator=None, quality=None, strategy="", alpha_effective=float("nan"), hop_gain=None,
                 excluded=None, roi=None, lambda_bar=None, started_afresh=False):
        self._record(mesh, u, shape=shape, spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                     success=success, status=status, message=message, nit=nit, energy_history=energy_history,
                     ncc_before=ncc_before, ncc_after=ncc_after, timings=timings, quality=quality,
                     strategy=strategy, alpha_effective=alpha_effective, solver_result=solver_result)
        self.blockmatch = blockmatch
        self.lambda_bar = None if lambda_bar is None else float(lambda_bar)
        self.started_afresh = bool(started_afresh)
        self._locator = locator
        self._grid = grid
        self._grid_element = None
        self._nodal_strain = None
        self.hop_gain = None if hop_gain is None else np.asarray(hop_gain, float)
        self.excluded = None if excluded is None else str(excluded)
        self.roi = None if roi is None else tuple(float(v) for v in roi)
        #: the :class:`femreg.echo.EchoRegion` the frames were cut to (what ``excluded`` says, as data; not saved)
        self.echo_region = None
        #: (n_axial, n_lateral) bool on the pixel grid, False where nothing was measured (outside the fan of a
        #: scan-converted frame, :func:`femreg.echo.fan_region`): fields there are NaN; None: everywhere
        self.data_mask = None

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

    @property
    def pixel_grid(self) -> PixelGrid:
        """The reference pixel grid (:class:`femreg.sampling.PixelGrid`)."""
        return PixelGrid.of(self.shape, self.spacing, self.origin)

    def displacement(self, points) -> np.ndarray:
        """u at ``points`` (n, 2) [x, y] mm -> (n, 2) [ux, uy] mm; NaN outside the mesh (and :attr:`data_mask`)."""
        return self._masked(points, sample_points(self.u, self.locator, points, ("ux", "uy")))

    def _masked(self, points, values):
        """``values`` at ``points`` NaN where the nearest pixel lies outside :attr:`data_mask`."""
        mask = getattr(self, "data_mask", None)
        if mask is None:
            return values
        pts = np.asarray(points, float).reshape(-1, 2)
        idx = np.rint((pts - np.asarray(self.origin, float)) / np.asarray(self.spacing, float)).astype(int)
        ok = np.all((idx >= 0) & (idx < np.asarray(mask.shape)), axis=1)
        off = ~ok
        off[ok] = ~mask[idx[ok, 0], idx[ok, 1]]
        values = np.array(values, float)
        values[off] = np.nan
        return values

    @property
    def nodal_strain(self) -> np.ndarray:
        """Recovered nodal strains (n_nodes, 3) [exx, eyy, exy]: the adaptive recovery with :attr:`recovery_weight`
        (:func:`femreg.fields.adaptive_strains`, :func:`femreg.fields.recovered_strains`)."""
        if self._nodal_strain is None:
            self._nodal_strain = adaptive_strains(self.mesh.p, self.mesh.t, self.u, self.recovery_weight)
        return self._nodal_strain

    @property
    def recovery_weight(self) -> float:
        """Weight of the L2 projection in the default (adaptive) recovered strain, 0 (the nodal average) to 1:
        :func:`femreg.fields.adaptive_weight` of :func:`femreg.fields.strain_roughness` where the refinement split
        elements (it found sharp features), else 0.  Without features the projection only spreads the
        registration's own defects (rotated uniform pairs of ``benchmarks/rotation_sweep.py``: up to +0.6 points);
        at a slip along the beam it rings about the displacement step (sliding-column pairs of
        ``benchmarks/layer_edges.py``: e_xx error 7.3 -> 7.8 %), so a result with slides keeps the average too."""
        if "_recovery_weight" not in self.__dict__:
            self._recovery_weight = (adaptive_weight(strain_roughness(self.mesh.p, self.mesh.t, self.u))
                                     if self._recovery_blends() else 0.0)
        return self._recovery_weight

    def _recovery_blends(self) -> bool:
        """Whether :attr:`recovery_weight` blends in the projection: the refinement split elements and found no
        slide (the property's docstring); a subclass's results may have their own rule."""
        rec = getattr(self, "refinement", None)
        passes = getattr(rec, "passes", None)
        split = (any(p.get("elements_after", 0) > p.get("elements", 0) for p in passes) if passes is not None
                 else getattr(rec, "base_size", None) is not None)
        return split and not len(getattr(rec, "slides", ()))

    def recovered(self, recovery: str | None = None) -> np.ndarray:
        """Recovered strains of method ``recovery`` (:data:`femreg.fields.RECOVERY_METHODS`; None: the default,
        :attr:`nodal_strain`): (n_nodes, 3), or per-element corner values (4, n_el, 3) for ``"edge"``."""
        if recovery is None or recovery == DEFAULT_RECOVERY:
            return self.nodal_strain
        cache = self.__dict__.setdefault("_recovered", {})
        if recovery not in cache:
            cache[recovery] = recovered_strains(self.mesh.p, self.mesh.t, self.u, recovery)
        return cache[recovery]

    def strain(self, points, strain: str = "recovered", recovery: str | None = None) -> np.ndarray:
        """Small strain at ``points`` (n, 2) mm -> (n, 3) [exx, eyy, exy], exy = (dux/dy + duy/dx) / 2;
        NaN outside the mesh.  ``strain="recovered"`` (default): the recovered strain interpolated bilinearly
        (:mod:`femreg.fields`; ``recovery`` its method, default the adaptive blend of the nodal average and the L2
        projection of the element-centre strains, continuous; ``"edge"`` keeps strain steps); ``"element"``: the
        gradient of the bilinear field, discontinuous across element edges (a point on an edge takes one of its
        elements)."""
        check_strain_mode(strain)
        return self._masked(points, sample_points(self.u, self.locator, points, ("exx", "eyy", "exy"),
                            nodal_strain=self.recovered(recovery) if strain == "recovered" else None))

    def pixel_points(self) -> np.ndarray:
        """Centres of the reference pixels, (n_axial * n_lateral, 2) mm, C order."""
        return self.pixel_grid.points()

    def on_grid(self, strain: str = "recovered", recovery: str | None = None) -> dict:
        """ux, uy, exx, eyy, exy on the reference pixel grid, each (n_axial, n_lateral) float64, NaN outside
        the mesh; strains as :meth:`strain` (``"recovered"`` or ``"element"``; ``recovery`` the method of the
        recovered strain, None the default)."""
        if check_strain_mode(strain) == "recovered" and recovery is not None and recovery != DEFAULT_RECOVERY:
            return self._masked_grid(sample_grid(self.u, self.locator, self.pixel_grid, "recovered",
                                                 nodal_strain=self.recovered(recovery)))
        if strain == "element":
            if self._grid_element is None:
                self._grid_element = self._masked_grid(sample_grid(self.u, self.locator, self.pixel_grid, "element"))
            return self._grid_element
        if self._grid is None:
            self._grid = self._masked_grid(sample_grid(self.u, self.locator, self.pixel_grid, "recovered",
                                                       nodal_strain=self.nodal_strain))
        return self._grid

    def _masked_grid(self, grid: dict) -> dict:
        """The pixel-grid fields NaN outside :attr:`data_mask` (in place)."""
        mask = getattr(self, "data_mask", None)
        if mask is not None:
            for v in grid.values():
                if isinstance(v, np.ndarray) and v.shape == mask.shape and v.dtype.kind == "f":
                    v[~mask] = np.nan
        return grid

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path, **extra):
        """Write the result as .npz, atomically: the contract of :mod:`femreg.io.results` (mesh, u, grid, pixel-grid
        fields, solver outcome, quality map, strategy), plus any ``extra`` arrays.  Returns the path."""
        return save_result(path, self, **extra)

    def summary(self, message: bool = True) -> str:
        """One line: regulariser, alpha, success, iterations, nodes, NCC before -> after and (``message``) the
        message; the command line leaves the message out where it follows as its error line."""
        tail = f", message={self.message!r}" if message else ""
        return (f"RegistrationResult(regularizer={self.regularizer!r}, alpha={self.alpha:g}, "
                f"success={self.success}, nit={self.nit}, n_nodes={self.mesh.p.shape[1]}, "
                f"ncc {self.ncc_before:.3f} -> {self.ncc_after:.3f}{tail})")

    def __repr__(self) -> str:
        return self.summary()


def displacement_at(spec, mesh, points, what: str):
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


def nodal_values(spec, mesh, what="initial"):
    """Nodal interleaved vector (2 n_nodes,) of ``mesh`` from a callable(points) -> (n, 2), a nodal vector, a
    RegistrationResult or a BlockMatchResult (``what`` names it in error messages)."""
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
        v = displacement_at(spec, mesh, pts, what)
    u = np.empty(2 * len(pts))
    u[0::2], u[1::2] = v[:, 0], v[:, 1]
    return u


#: The result class of convex / sector frames (:class:`femreg.geometry.BeamResult`, which registers itself on
#: import through :func:`register_beam_result`): this module cannot import femreg.geometry, which builds on it.
_BEAM_RESULT: list = []


def register_beam_result(cls) -> None:
    """Make :func:`load_result` build ``cls(mesh, u, geometry=..., **kw)`` for files with a probe geometry."""
    _BEAM_RESULT[:] = [cls]


def load_result(path) -> RegistrationResult:
    """Read a result ``.npz`` (the contract of :mod:`femreg.io.results`) as a :class:`RegistrationResult` (a
    :class:`femreg.geometry.BeamResult` for convex / sector frames).

    The one reader of the contract (``femreg.load_result`` and ``femreg.io.load_result`` are this function).
    Raises :class:`~femreg.errors.FileFormatError` naming the missing key or bad shape when the file is not a
    result."""
    from .volume_result import is_volume_result, load_volume_result

    if is_volume_result(path):          # a volume's result (femreg.volume_result)
        return load_volume_result(path)
    mesh, u, kw, element_grid = read_result(path)
    base = kw.pop("refined_from", None)
    slides = kw.pop("slides", ())
    auto = kw.pop("auto_alpha", None)
    mask = kw.pop("data_mask", None)
    geometry = kw.pop("geometry", None)
    weight = kw.pop("recovery_weight", None)
    if geometry is not None and _BEAM_RESULT:     # convex / sector frames: samples at their physical positions
        res = _BEAM_RESULT[0](mesh, u, geometry=geometry, **kw)
    else:
        res = RegistrationResult(mesh, u, **kw)
    res._grid_element = element_grid
    if weight is not None:
        res._recovery_weight = weight            # the strains as the file's grid holds them
    res.auto_alpha = auto
    res.data_mask = mask
    if base is not None or len(slides):     # what the inversion and new meshes read
        from .result_base import RefinementRecord

        res.refinement = RefinementRecord(passes=None, base_size=base, slides=tuple(slides))
    return res
