"""The result of a volume registration: :class:`VolumeResult`, a nodal displacement on a trilinear hexahedral mesh
with the API of :class:`femreg.result.RegistrationResult` in 3D (``displacement`` (n, 3), ``strain`` (n, 6) in
:data:`~femreg.volume_fields.STRAIN_COMPONENTS_3D` order, ``quality``, ``on_grid``, ``success`` and ``message``,
``save`` / :func:`load_volume_result`, ``write_vtu``, ``write_xdmf``); :class:`SweptResult`, the same for the
volumes of a swept probe (:mod:`femreg.swept`), read at the samples' physical positions.
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from .errors import FileFormatError, InputError
from .fields import check_strain_mode
from .probes import as_geometry
from .result_base import ResultRecord, read_auto_alpha
from .volume_fields import (DISPLACEMENT_COMPONENTS_3D, FIELDS_3D, SAMPLE_CHUNK, STRAIN_COMPONENTS_3D, HexLocator,
                            element_strains_3d, recovered_strains_3d)

__all__ = ["VolumeResult", "SweptResult", "load_volume_result", "is_volume_result", "beam_strain_3d",
           "VOLUME_RESULT_KIND", "BEAM_STRAIN_COMPONENTS_3D"]

#: ``kind`` entry of a saved volume result (.npz).
VOLUME_RESULT_KIND = "femreg-volume-result-1"


class VolumeResult(ResultRecord):
    """A registered displacement field of a volume pair on a hexahedral mesh.

    Attributes
    ----------
    mesh : skfem.MeshHex1
        mm; ``mesh.p`` rows axial x, lateral y, elevational z.
    u : (3 n_nodes,) float, mm
        Nodal displacement, interleaved ``[ux0, uy0, uz0, ux1, ...]`` (scikit-fem DOF order).
    strain_components, displacement_components : tuple of str
        Names of the columns of :meth:`strain` and :meth:`displacement`.
    shape, spacing, origin
        Reference voxel grid (voxel [i, j, k] centre at ``origin + (i, j, k) * spacing``).
    success, status, message, nit, energy_history, ncc_before, ncc_after, timings, regularizer, alpha,
    alpha_effective, strategy
        As in :class:`femreg.result.RegistrationResult`.
    quality : (n_elements,) float or None
        Per-element NCC of reference and warped moving volume at the result.
    excluded : str or None
        What of the volume was left out of the mesh and why (:mod:`femreg.echo_volume`); None: nothing.
    roi : (x0, x1, y0, y1, z0, z1) mm or None
        The box registered when not the whole volume.
    auto_alpha : femreg.autoalpha.AutoAlpha or None
        With ``alpha="auto"``: the choice and the rule's data over the candidate grid (saved with the result).
    """

    strain_components = STRAIN_COMPONENTS_3D
    excluded = None
    roi = None
    displacement_components = DISPLACEMENT_COMPONENTS_3D
    ndim = 3

    def __init__(self, mesh, u, *, shape, spacing, origin, regularizer="", alpha=float("nan"), success=False,
                 status=-1, message="", nit=0, energy_history=(), ncc_before=float("nan"), ncc_after=float("nan"),
                 timings=None, quality=None, strategy="", alpha_effective=float("nan"), solver_result=None):
        self._record(mesh, u, shape=shape, spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                     success=success, status=status, message=message, nit=nit, energy_history=energy_history,
                     ncc_before=ncc_before, ncc_after=ncc_after, timings=timings, quality=quality,
                     strategy=strategy, alpha_effective=alpha_effective, solver_result=solver_result)
        self._locator = None
        self._nodal_strain = None
        self._grids = {}

    @property
    def locator(self) -> HexLocator:
        if self._locator is None:
            self._locator = HexLocator(self.mesh)
        return self._locator

    @property
    def nodal_strain(self) -> np.ndarray:
        """Recovered nodal strains (n_nodes, 6) (:func:`femreg.volume_fields.recovered_strains_3d`)."""
        if self._nodal_strain is None:
            self._nodal_strain = recovered_strains_3d(self.mesh, self.u)
        return self._nodal_strain

    @staticmethod
    def _points(points) -> np.ndarray:
        p = np.asarray(points, float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"points of a volume result must be (n, 3) [x, y, z] mm, got shape {p.shape}")
        return p

    def displacement(self, points) -> np.ndarray:
        """u at ``points`` (n, 3) mm -> (n, 3) [ux, uy, uz] mm; NaN outside the mesh."""
        f = self.locator.sample(self.u, self._points(points))
        return np.column_stack([f[k] for k in DISPLACEMENT_COMPONENTS_3D])

    def strain(self, points, strain: str = "recovered") -> np.ndarray:
        """Small strain at ``points`` (n, 3) mm -> (n, 6) in :attr:`strain_components` order (tensor shear);
        NaN outside the mesh.  ``"recovered"`` (default): nodal average of the element-centre strains, trilinear
        in between; ``"element"``: the gradient of the trilinear field at the point."""
        check_strain_mode(strain)
        f = self.locator.sample(self.u, self._points(points),
                                nodal_strain=self.nodal_strain if strain == "recovered" else None)
        return np.column_stack([f[k] for k in STRAIN_COMPONENTS_3D])

    def voxel_axes(self):
        return [self.origin[a] + self.spacing[a] * np.arange(self.shape[a]) for a in range(3)]

    def voxel_points(self) -> np.ndarray:
        """Centres of the reference voxels, (n_voxels, 3) mm, C order."""
        X = np.meshgrid(*self.voxel_axes(), indexing="ij")
        return np.column_stack([x.ravel() for x in X])

    def on_grid(self, strain: str = "recovered") -> dict:
        """``ux, uy, uz, exx, eyy, ezz, exy, exz, eyz, quality`` on the reference voxel grid, each
        (n_x, n_y, n_z) float64 (NaN outside the mesh; ``quality`` the element NCC of each voxel's element), on the
        grid of :attr:`spacing` and :attr:`origin`: the input of :func:`femreg.volplot.plot_volume_slices`."""
        check_strain_mode(strain)
        if strain not in self._grids:
            self._grids[strain] = self._sample_slabs(strain)
        return self._grids[strain]

    def _slab_points(self, i0: int, i1: int) -> np.ndarray:
        """Physical points (n, 3) mm of the grid's axial slab ``i0:i1``, C order."""
        x, y, z = self.voxel_axes()
        X = np.meshgrid(x[i0:i1], y, z, indexing="ij")
        return np.column_stack([c.ravel() for c in X])

    def _sample_slabs(self, strain: str) -> dict:
        """Every field at the points of :meth:`_slab_points`, ``shape`` each."""
        ns = self.nodal_strain if strain == "recovered" else None
        out = {k: np.empty(self.shape) for k in FIELDS_3D + ("quality",)}
        # axial slabs of about SAMPLE_CHUNK points: the sampling temporaries stay small whatever the volume
        step = max(1, SAMPLE_CHUNK // (self.shape[1] * self.shape[2]))
        for i0 in range(0, self.shape[0], step):
            pts = self._slab_points(i0, min(self.shape[0], i0 + step))
            sl = (slice(i0, i0 + step), slice(None), slice(None))
            n = (min(self.shape[0], i0 + step) - i0,) + self.shape[1:]
            for k, v in self.locator.sample(self.u, pts, nodal_strain=ns).items():
                out[k][sl] = v.reshape(n)
            if self.quality is None:
                out["quality"][sl] = np.nan
            else:
                inside, e, _, _ = self.locator.locate(pts)
                cell = self.locator.cell[e[0], e[1], e[2]]
                out["quality"][sl] = np.where(inside, self.quality[cell], np.nan).reshape(n)
        return out

    # -- files ----------------------------------------------------------------------------------------------
    def save(self, path, **extra):
        """Write the result as .npz (mesh, u, voxel grid, solver outcome, quality, and ``extra`` arrays);
        returns the path."""
        path = Path(path)
        np.savez(path, kind=np.array(VOLUME_RESULT_KIND), mesh_points=self.mesh.p, mesh_cells=self.mesh.t,
                 u=self.u, shape=np.array(self.shape), spacing=self.spacing, origin=self.origin,
                 regularizer=np.array(self.regularizer), alpha=self.alpha, success=self.success, status=self.status,
                 message=np.array(self.message), nit=self.nit, energy_history=self.energy_history,
                 ncc_before=self.ncc_before, ncc_after=self.ncc_after, strategy=np.array(self.strategy),
                 alpha_effective=self.alpha_effective,
                 quality=np.full(self.mesh.t.shape[1], np.nan) if self.quality is None else self.quality,
                 strain_components=np.array(self.strain_components), **self._region_record(),
                 **self._auto_alpha_record(), **extra)
        return path

    def _region_record(self) -> dict:
        """``excluded`` / ``roi`` entries of the saved file (only when the result has them)."""
        out = {} if self.excluded is None else {"excluded": np.array(str(self.excluded))}
        return out if self.roi is None else dict(out, roi=np.asarray(self.roi, float))

    def write_vtu(self, path):
        """ParaView file (.vtu, meshio): hexahedra with point data ``u`` (n, 3) mm and the recovered strains,
        cell data the element-centre strains and ``quality``.  Returns the path."""
        return self._write(path, "vtu")

    def write_xdmf(self, path):
        """As :meth:`write_vtu`, in XDMF (+ HDF5 heavy data next to it, ``<stem>.h5``).  Returns the path."""
        return self._write(path, "xdmf")

    def _write(self, path, file_format):
        from .optional import require

        meshio = require("meshio", feature="VTU/XDMF export")

        # VTK hexahedron order: the bottom face (z low) counter-clockwise, then the top face
        p = self.mesh.p
        t = self.mesh.t
        c = p[:, t]                                                   # (3, 8, n_el)
        hi = c.max(axis=1)
        side = np.isclose(c, hi[:, None, :])                          # (3, 8, n_el) upper side per axis
        order = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
        cells = np.empty((t.shape[1], 8), np.int64)
        for k, (i, j, l) in enumerate(order):
            m = (side[0] == bool(i)) & (side[1] == bool(j)) & (side[2] == bool(l))
            cells[:, k] = t[np.argmax(m, axis=0), np.arange(t.shape[1])]
        ns = self.nodal_strain
        es = element_strains_3d(self.mesh, self.u)
        point_data = {"u": self.u.reshape(-1, 3)}
        cell_data = {}
        for k, name in enumerate(STRAIN_COMPONENTS_3D):
            point_data[name] = ns[:, k]
            cell_data[name + "_element"] = [es[:, k]]
        if self.quality is not None:
            cell_data["quality"] = [self.quality]
        meshio.Mesh(p.T, [("hexahedron", cells)], point_data=point_data, cell_data=cell_data).write(
            str(path), file_format=file_format)
        return Path(path)

    def __repr__(self) -> str:
        return (f"VolumeResult(regularizer={self.regularizer!r}, alpha={self.alpha:g}, success={self.success}, "
                f"nit={self.nit}, n_nodes={self.mesh.p.shape[1]}, ncc {self.ncc_before:.3f} -> "
                f"{self.ncc_after:.3f}, message={self.message!r})")


#: Strain components in a swept probe's beam frame: along the ray (r), across the lines (l), across the frames (p).
BEAM_STRAIN_COMPONENTS_3D = ("err", "ell", "epp", "erl", "erp", "elp")


class SweptResult(VolumeResult):
    """A :class:`VolumeResult` of a swept probe's volumes (:mod:`femreg.swept`): mesh, ``u``, ``displacement`` and
    ``strain`` in physical Cartesian coordinates (x depth, y lateral, z elevational, mm); ``shape``, ``spacing``,
    ``origin`` describe the sample grid (``spacing`` = (dr mm, line pitch mm or deg, frame step deg), as given to
    ``femreg.register``), ``geometry`` the :class:`femreg.probes.Swept` mapping, ``cartesian`` the
    ``(shape, spacing, origin)`` of the scan-converted voxel grid that was registered.  :meth:`on_grid` gives
    every field at the samples' physical positions, (n_samples, n_lines, n_frames) each (NaN outside the mesh)."""

    def __init__(self, *args, geometry, cartesian, **kw):
        super().__init__(*args, **kw)
        self.geometry = geometry
        self.cartesian = (tuple(int(v) for v in cartesian[0]), np.asarray(cartesian[1], float),
                          np.asarray(cartesian[2], float))

    @classmethod
    def of(cls, res: VolumeResult, *, geometry, shape, spacing, origin, cartesian) -> "SweptResult":
        """The registration ``res`` of the scan-converted volumes as the result of the swept pair."""
        out = cls(res.mesh, res.u, shape=shape, spacing=spacing, origin=origin, regularizer=res.regularizer,
                  alpha=res.alpha, success=res.success, status=res.status, message=res.message, nit=res.nit,
                  energy_history=res.energy_history, ncc_before=res.ncc_before, ncc_after=res.ncc_after,
                  timings=res.timings, quality=res.quality, strategy=res.strategy,
                  alpha_effective=res.alpha_effective, solver_result=res.solver_result, geometry=geometry,
                  cartesian=cartesian)
        out.excluded, out.roi = res.excluded, res.roi
        for k in ("initial_info", "hop_gain"):
            if hasattr(res, k):
                setattr(out, k, getattr(res, k))
        return out

    def _slab_points(self, i0: int, i1: int) -> np.ndarray:
        i, j, k = np.meshgrid(np.arange(i0, i1), np.arange(self.shape[1]), np.arange(self.shape[2]), indexing="ij")
        return self.geometry.index_to_physical(np.stack([i.ravel(), j.ravel(), k.ravel()]), self.shape,
                                               self.spacing, self.origin)

    def voxel_points(self) -> np.ndarray:
        """Physical positions of the samples, (n_samples n_lines n_frames, 3) mm, C order."""
        return self._slab_points(0, self.shape[0])

    def sample_positions(self) -> tuple:
        """``(X, Y, Z)`` physical positions of the samples, ``shape`` each, mm."""
        return self.geometry.sample_positions(self.shape, self.spacing, self.origin)

    def cartesian_grid(self, strain: str = "recovered") -> dict:
        """Every field (:meth:`VolumeResult.on_grid`) on the scan-converted Cartesian voxel grid
        (:attr:`cartesian`): the input of :func:`femreg.volplot.plot_volume_slices` with its spacing and origin."""
        n, h, o = self.cartesian
        grid = VolumeResult(self.mesh, self.u, shape=n, spacing=h, origin=o, quality=self.quality)
        grid._nodal_strain, grid._locator = self._nodal_strain, self._locator
        return grid.on_grid(strain)

    def strain(self, points, strain: str = "recovered", frame: str = "xyz") -> np.ndarray:
        """Small strain at physical ``points`` (n, 3) mm: ``frame="xyz"`` (n, 6) as :meth:`VolumeResult.strain`;
        ``"beam"`` the same tensor in the local beam axes (along the ray, across the lines, across the frames:
        :meth:`femreg.probes.Swept.beam_axes`), :data:`BEAM_STRAIN_COMPONENTS_3D` order."""
        if frame not in ("xyz", "beam"):
            raise InputError(f"frame must be 'xyz' or 'beam', got {frame!r}")
        e = super().strain(points, strain)
        return beam_strain_3d(e, self.geometry.beam_axes(self._points(points))) if frame == "beam" else e

    def on_grid(self, strain: str = "recovered", frame: str = "xyz") -> dict:
        """``ux, uy, uz`` (mm), the six strains and ``quality`` at every sample, ``shape`` each, NaN outside the
        mesh; with ``frame="beam"`` also :data:`BEAM_STRAIN_COMPONENTS_3D` (the strain in the beam axes)."""
        if frame not in ("xyz", "beam"):
            raise InputError(f"frame must be 'xyz' or 'beam', got {frame!r}")
        out = super().on_grid(strain)
        if frame == "beam" and "err" not in out:
            E = np.column_stack([out[k].ravel() for k in STRAIN_COMPONENTS_3D])
            b = beam_strain_3d(E, self.geometry.beam_axes(self.voxel_points()))
            out.update({k: b[:, c].reshape(self.shape) for c, k in enumerate(BEAM_STRAIN_COMPONENTS_3D)})
        return out

    def save(self, path, **extra):
        n, h, o = self.cartesian
        return super().save(path, geometry=np.array(json.dumps(self.geometry.to_dict())),
                            cartesian_shape=np.array(n), cartesian_spacing=h, cartesian_origin=o, **extra)

    def __repr__(self) -> str:
        return "Swept" + super().__repr__()


def beam_strain_3d(strain, axes) -> np.ndarray:
    """Small strains (n, 6) in :data:`STRAIN_COMPONENTS_3D` order rotated into local axes ``axes`` (n, 3, 3)
    (columns orthonormal): E' = Q^T E Q, (n, 6) in :data:`BEAM_STRAIN_COMPONENTS_3D` order."""
    e = np.asarray(strain, float).reshape(-1, 6)
    E = np.empty((len(e), 3, 3))
    E[:, 0, 0], E[:, 1, 1], E[:, 2, 2] = e[:, 0], e[:, 1], e[:, 2]
    E[:, 0, 1] = E[:, 1, 0] = e[:, 3]
    E[:, 0, 2] = E[:, 2, 0] = e[:, 4]
    E[:, 1, 2] = E[:, 2, 1] = e[:, 5]
    B = np.einsum("nij,njk,nkl->nil", np.swapaxes(axes, 1, 2), E, axes)
    return np.column_stack([B[:, 0, 0], B[:, 1, 1], B[:, 2, 2], B[:, 0, 1], B[:, 0, 2], B[:, 1, 2]])


def is_volume_result(path) -> bool:
    """Whether ``path`` is an .npz written by :meth:`VolumeResult.save` (False for anything unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return "kind" in z.files and str(z["kind"]) == VOLUME_RESULT_KIND
    except Exception:  # noqa: BLE001 - anything unreadable is not a volume result (its own reader says why)
        return False


def load_volume_result(path) -> VolumeResult:
    """Read a volume result written by :meth:`VolumeResult.save`; FileFormatError naming what is missing."""
    from skfem import MeshHex1

    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise FileFormatError(f"{path}: not a readable .npz ({exc})") from None
    with z:
        if "kind" not in z or str(z["kind"]) != VOLUME_RESULT_KIND:
            raise FileFormatError(f"{path}: not a femreg volume result (no kind {VOLUME_RESULT_KIND!r})")
        missing = [k for k in ("mesh_points", "mesh_cells", "u", "shape", "spacing", "origin") if k not in z]
        if missing:
            raise FileFormatError(f"{path}: volume result lacks {', '.join(missing)}")
        mesh = MeshHex1(np.asarray(z["mesh_points"], float), np.asarray(z["mesh_cells"], np.int64))
        q = np.asarray(z["quality"], float)
        kw = {}
        cls = VolumeResult
        if "geometry" in z:             # a swept probe's result (femreg.swept): the mapping and the registered grid
            try:
                geo = as_geometry(json.loads(str(z["geometry"])))
                kw = dict(geometry=geo, cartesian=(tuple(int(v) for v in z["cartesian_shape"]),
                                                   z["cartesian_spacing"], z["cartesian_origin"]))
            except (ValueError, KeyError, InputError) as exc:
                raise FileFormatError(f"{path}: unreadable swept geometry ({exc})") from None
            cls = SweptResult
        res = cls(mesh, z["u"], shape=tuple(z["shape"]), spacing=z["spacing"], origin=z["origin"],
                  regularizer=str(z["regularizer"]), alpha=float(z["alpha"]), success=bool(z["success"]),
                  status=int(z["status"]), message=str(z["message"]), nit=int(z["nit"]),
                  energy_history=z["energy_history"], ncc_before=float(z["ncc_before"]),
                  ncc_after=float(z["ncc_after"]), strategy=str(z["strategy"]),
                  alpha_effective=float(z["alpha_effective"]), quality=q, **kw)
        if "excluded" in z:
            res.excluded = str(z["excluded"])
        if "roi" in z:
            roi = np.asarray(z["roi"], float).ravel()
            if roi.size != 6 or not np.all(np.isfinite(roi)):
                raise FileFormatError(f"{path}: 'roi' must be six finite numbers x0 x1 y0 y1 z0 z1 (mm)")
            res.roi = tuple(float(v) for v in roi)
        if "auto_alpha" in z:
            res.auto_alpha = read_auto_alpha(z["auto_alpha"], path)
        return res
