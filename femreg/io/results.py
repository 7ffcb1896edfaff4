"""Registration results on disk: the ``.npz`` contract, and VTU / XDMF exports through meshio for ParaView.

The ``.npz`` contract, written by :func:`save_result` (``res.save(path)``) and read by :func:`read_result` (from
which :func:`femreg.load_result` builds a :class:`femreg.RegistrationResult`); the first six keys are required:

=================  ==============================  ===================================================
key                shape                           meaning
=================  ==============================  ===================================================
mesh_points        (2, n_nodes) mm                 node coordinates, row 0 axial x, row 1 lateral y
mesh_cells         (4, n_el) int                   quad connectivity (counter-clockwise, as skfem)
u                  (2*n_nodes,) mm                 nodal displacement, interleaved [ux0, uy0, ux1, ...]
spacing, origin    (2,) mm                         reference pixel grid
shape              (2,) int                        reference image shape (axial, lateral)
ux uy exx eyy exy  (n_axial, n_lateral)            fields on the reference pixel grid, NaN outside mesh
regularizer        str                             regulariser name
alpha, success,    scalars                         optimiser outcome (scipy OptimizeResult-like)
nit, message
ncc_before/after   scalar                          NCC of reference and warped moving image
energy_history     (nit+1,)                        objective per Gauss-Newton iterate
quality            (n_el,)                         per-element quality map (optional)
strategy           str                             registration strategy (optional)
strain             str                             how the grid strains were evaluated: "recovered" or
                                                   "element" (optional; absent: served as written --
                                                   files of earlier versions hold element strains)
excluded           str                             what of the frames was not registered and why
                                                   (optional; absent: the whole frames)
roi                (4,) mm                         the rectangle registered, x0 x1 y0 y1 (optional)
data_mask          (n_axial, n_lateral) bool       False where nothing was measured (outside the fan of a
                                                   scan-converted frame; optional; absent: everywhere)
refined_from       (2,) mm                         median element size (axial, lateral) of the mesh adaptive
                                                   refinement started from (optional; absent: not refined)
slides             (k,) mm                         lateral positions where the refinement found tissue sliding
                                                   along the beam (optional; absent: none)
lambda_bar         float                           lambda_bar of the momentum regulariser that solved (2 or 9
                                                   for R_P_sigma; optional; absent: another regulariser)
started_afresh     bool                            a track's increment started from the strategy's own start,
                                                   not the previous increment (optional; absent: read from
                                                   the message, as files of earlier versions say it)
recovery           str                             recovered strains: the method of
                                                   :func:`femreg.fields.recovered_strains` (optional;
                                                   absent: files of earlier versions, nodal averages)
recovery_weight    float                           the adaptive recovery's projection weight (optional;
                                                   absent: 0, the nodal average)
auto_alpha         str (JSON)                      ``alpha="auto"``: the choice and the rule's data over
                                                   the candidate grid (optional;
                                                   :class:`femreg.result_base.AutoAlpha`)
=================  ==============================  ===================================================

Strains are the small-strain tensor components ``exx = dux/dx``, ``eyy = duy/dy``,
``exy = (dux/dy + duy/dx)/2`` (tensor shear, not engineering shear); the grid holds the recovered strain
(:func:`femreg.fields.recovered_strains`) in files written by this version.
"""
from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError, pass_as
from ..fields import element_strains, nodal_average  # noqa: F401  (part of this module's API; one implementation)
from ..mesh import check_mesh  # noqa: F401  (also femreg.io.results.check_mesh)
from .._atomic import atomic_savez
from ..result_base import FRESH_NOTE, read_auto_alpha
from .checks import fail

__all__ = ["RESULT_KEYS", "GRID_FIELDS", "read_result", "save_result", "element_strains",
           "nodal_average",
           "mesh_fields", "write_vtu", "write_xdmf", "export_result"]

RESULT_KEYS = ("mesh_points", "mesh_cells", "u", "spacing", "origin", "shape", "ux", "uy", "exx", "eyy", "exy",
               "regularizer", "alpha", "success", "nit", "message", "ncc_before", "ncc_after", "energy_history",
               "quality", "strategy", "strain", "excluded", "roi", "recovery", "recovery_weight", "refined_from",
               "slides", "auto_alpha", "data_mask", "lambda_bar", "started_afresh")
REQUIRED = ("mesh_points", "mesh_cells", "u", "spacing", "origin", "shape")
GRID_FIELDS = ("ux", "uy", "exx", "eyy", "exy")


def _scalar(v):
    v = np.asarray(v)
    return v.item() if v.ndim == 0 else v


def mesh_fields(mesh_points, mesh_cells, u, *, strains="both", point_data=None, cell_data=None,
                recovery_weight=None):
    """meshio-ready (points (n, 3), cells, point_data, cell_data) for a registration result.

    Point data ``displacement`` (n_nodes, 3) with z = 0; strains ``exx``, ``eyy``, ``exy`` as element-centre cell
    data (``strains='cell'``), the recovered nodal strains (:func:`femreg.fields.recovered_strains`, what the
    pictures show; ``recovery_weight`` the result's adaptive weight, None: from ``u`` alone) as point data
    (``'point'``), or both (default).
    """
    p, t, uu = check_mesh(mesh_points, mesh_cells, u)
    if strains not in ("cell", "point", "both", "none", None):
        raise InputError(f"strains must be 'cell', 'point', 'both' or 'none', got {strains!r}")
    n = p.shape[1]
    pts = np.zeros((n, 3))
    pts[:, :2] = p.T
    disp = np.zeros((n, 3))
    disp[:, 0], disp[:, 1] = uu[0::2], uu[1::2]
    pdata = {"displacement": disp}
    cdata = {}
    if strains in ("cell", "point", "both"):
        e = element_strains(p, t, uu)
        if strains in ("cell", "both"):
            cdata.update({name: [e[:, k]] for k, name in enumerate(("exx", "eyy", "exy"))})
        if strains in ("point", "both"):
            from ..fields import adaptive_strains, recovered_strains

            en = (recovered_strains(p, t, uu) if recovery_weight is None
                  else adaptive_strains(p, t, uu, float(recovery_weight)))
            pdata.update({name: en[:, k] for k, name in enumerate(("exx", "eyy", "exy"))})
    for k, v in (point_data or {}).items():
        v = np.asarray(v, dtype=float)
        if v.shape[0] != n:
            raise InputError(f"point_data[{k!r}] has {v.shape[0]} rows, mesh has {n} nodes")
        pdata[k] = v
    for k, v in (cell_data or {}).items():
        v = np.asarray(v, dtype=float)
        if v.shape[0] != t.shape[1]:
            raise InputError(f"cell_data[{k!r}] has {v.shape[0]} rows, mesh has {t.shape[1]} cells")
        cdata[k] = [v]
    return pts, [("quad", t.T)], pdata, cdata


def write_vtu(path, mesh_points, mesh_cells, u, *, strains="both", point_data=None, cell_data=None,
              recovery_weight=None):
    """Write the mesh, nodal displacement (point data, z = 0) and strains to a VTU file (ParaView).

    Parameters
    ----------
    mesh_points : (2, n_nodes) mm; mesh_cells : (4, n_el) int; u : (2*n_nodes,) mm interleaved.
    strains : {'both', 'cell', 'point', 'none'}
        Element-centre strains as cell data and/or their nodal averages as point data.
    point_data, cell_data : dict of extra arrays, (n_nodes, ...) / (n_el, ...).
    recovery_weight : float, optional
        The result's adaptive recovery weight (:attr:`femreg.registration.RegistrationResult.recovery_weight`).
    """
    from ..optional import require

    meshio = require("meshio", feature="VTU/XDMF export")

    pts, cells, pdata, cdata = mesh_fields(mesh_points, mesh_cells, u, strains=strains, point_data=point_data,
                                           cell_data=cell_data, recovery_weight=recovery_weight)
    meshio.Mesh(pts, cells, point_data=pdata, cell_data=cdata).write(str(path), file_format="vtu")
    return Path(path)


def write_xdmf(path, mesh_points, mesh_cells, u, *, strains="both", point_data=None, cell_data=None,
              recovery_weight=None):
    """As :func:`write_vtu`, in XDMF (+ HDF5 heavy data next to it, ``<stem>.h5``)."""
    from ..optional import require

    meshio = require("meshio", feature="VTU/XDMF export")

    pts, cells, pdata, cdata = mesh_fields(mesh_points, mesh_cells, u, strains=strains, point_data=point_data,
                                           cell_data=cell_data, recovery_weight=recovery_weight)
    meshio.Mesh(pts, cells, point_data=pdata, cell_data=cdata).write(str(path), file_format="xdmf")
    return Path(path)


# ---------------------------------------------------------------------------------------------- npz results

def _from_object(res) -> dict:
    """Contract keys of an engine result object (``.mesh``, ``.u``, ``on_grid()``, scalars)."""
    out = {}
    mesh = getattr(res, "mesh", None)
    if mesh is not None:
        out["mesh_points"] = np.asarray(mesh.p)
        out["mesh_cells"] = np.asarray(mesh.t)
    if callable(getattr(res, "on_grid", None)):
        out.update(res.on_grid())                   # pixel-grid fields (the object's ux/uy are nodal)
        out["strain"] = "recovered"                 # what on_grid() gives by default
        from ..fields import DEFAULT_RECOVERY

        out["recovery"] = DEFAULT_RECOVERY
        if getattr(res, "mesh", None) is not None and hasattr(res, "recovery_weight"):
            out["recovery_weight"] = float(res.recovery_weight)
    base = getattr(getattr(res, "refinement", None), "base_size", None)
    if base is not None:
        out["refined_from"] = np.asarray(base, float)
    slides = getattr(getattr(res, "refinement", None), "slides", ())
    if len(slides):
        out["slides"] = np.asarray(slides, float)
    record = getattr(res, "_auto_alpha_record", None)
    if callable(record):
        out.update(record())
    for k in RESULT_KEYS:
        if k not in out and hasattr(res, k):
            v = getattr(res, k)
            if v is not None and not callable(v):
                out[k] = v
    return out


def as_result_dict(result) -> dict:
    """A result as a plain dict of the contract's keys (and any extra arrays of a file): from a path (.npz), a
    mapping, or an engine result object."""
    if isinstance(result, (str, os.PathLike)):
        return _read(result)
    if hasattr(result, "keys"):
        return {k: _scalar(result[k]) for k in result.keys()}
    return _from_object(result)


#: Where results come from, for messages about files that are not one.
_RESULT_FILES = ("femreg register -o FILE.npz; femreg track: OUT/frame_KKK.npz; femreg invert -o FILE.npz")


def _read(path) -> dict:
    """The validated contents of a result ``.npz``; scalars become Python scalars."""
    path = Path(path)
    if path.is_dir():                    # e.g. a `femreg track` folder: one result file per frame
        found = sorted(path.glob("*.npz"))
        raise fail(path, "a folder, not a result file" + (f": name one of its {len(found)} result files, e.g. "
                                                          f"{found[-1]}" if found else ""))
    if not path.is_file():
        raise fail(path, "no such result file")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):     # a .npy: one array (frames?), not a result
            raise ValueError(f"one array of shape {np.shape(z)}")
        with z:
            out = {k: _scalar(z[k]) for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError, RuntimeError, NotImplementedError) as exc:
        if path.suffix.lower() != ".npz":
            raise fail(path, f"not a result file: a result is a .npz ({_RESULT_FILES})") from None
        raise fail(path, f"not a readable .npz result ({type(exc).__name__}: {exc})") from None
    missing = [k for k in REQUIRED if k not in out]
    if missing and all(k in out for k in ("exx", "ref_frame", "quality")):
        raise fail(path, "an elastogram of `femreg elastogram` (a normalised strain image, no displacement): its "
                         "picture is elastogram.png beside it and `femreg measure` reads it; plotting, inverting or "
                         "exporting need a registration result (`femreg register LOOP --pair I J`)")
    if missing and all(k in out for k in ("ref", "mov", "exx", "u")):
        raise fail(path, "a pair checkpoint of `femreg elastogram` (no mesh): register the pair with `femreg "
                         f"register LOOP --pair {out['ref']} {out['mov']}` for a result to plot or invert")
    if missing and str(out.get("format", "")).startswith("femreg-inversion"):
        raise fail(path, "a shear-modulus image, not a registration result: " + pass_as(
            "read it with femreg.load_inversion", "`femreg plot` draws it; this command reads a registration result"))
    if missing:
        raise fail(path, f"not a femreg result: missing key(s) {', '.join(missing)}")
    try:
        check_mesh(out["mesh_points"], out["mesh_cells"], out["u"], where="result")
    except InputError as exc:
        raise fail(path, str(exc)) from None
    shape = np.asarray(out["shape"])
    if shape.shape != (2,) or shape.dtype.kind not in "iu" or shape.min() < 1:
        raise fail(path, f"key 'shape' must be two positive integers, got {out['shape']!r}")
    for k in ("spacing", "origin"):
        v = np.asarray(out[k], dtype=float) if np.asarray(out[k]).dtype.kind in "iuf" else None
        if v is None or v.shape != (2,) or not np.all(np.isfinite(v)) or (k == "spacing" and v.min() <= 0):
            raise fail(path, f"key {k!r} must be two finite numbers{' > 0' if k == 'spacing' else ''}, "
                             f"got {out[k]!r}")
    if "data_mask" in out and (np.asarray(out["data_mask"]).dtype != bool
                               or np.shape(out["data_mask"]) != tuple(np.ravel(out["shape"]).astype(int))):
        raise fail(path, f"key 'data_mask' must be a bool array of the grid's shape {tuple(np.ravel(out['shape']))}, "
                         f"got {np.asarray(out['data_mask']).dtype} {np.shape(out['data_mask'])}")
    if "roi" in out and (np.shape(out["roi"]) != (4,) or np.asarray(out["roi"]).dtype.kind not in "iuf"
                         or not np.all(np.isfinite(np.asarray(out["roi"], float)))):
        raise fail(path, f"key 'roi' must be four finite numbers x0 x1 y0 y1 (mm), got {out['roi']!r}")
    if "refined_from" in out and (np.shape(out["refined_from"]) != (2,)
                                  or np.asarray(out["refined_from"]).dtype.kind not in "iuf"
                                  or not np.all(np.asarray(out["refined_from"], float) > 0)):
        raise fail(path, f"key 'refined_from' must be two element sizes > 0 (mm), got {out['refined_from']!r}")
    if "lambda_bar" in out and (np.ndim(out["lambda_bar"]) != 0 or np.asarray(out["lambda_bar"]).dtype.kind not in "iuf"
                                or not np.isfinite(float(out["lambda_bar"])) or float(out["lambda_bar"]) < 0):
        raise fail(path, f"key 'lambda_bar' must be a number >= 0, got {out['lambda_bar']!r}")
    if "started_afresh" in out and not isinstance(out["started_afresh"], (bool, np.bool_)):
        raise fail(path, f"key 'started_afresh' must be a bool, got {out['started_afresh']!r}")
    if "slides" in out and (np.ndim(out["slides"]) != 1 or np.asarray(out["slides"]).dtype.kind not in "iuf"
                            or not np.all(np.isfinite(np.asarray(out["slides"], float)))):
        raise fail(path, f"key 'slides' must be finite lateral positions (mm), got {out['slides']!r}")
    n_el = np.shape(out["mesh_cells"])[1]
    if "quality" in out and np.shape(out["quality"]) != (n_el,):
        raise fail(path, f"key 'quality' must have one value per element ({n_el},), got {np.shape(out['quality'])}")
    for k in GRID_FIELDS:
        if k in out and np.shape(out[k]) != tuple(shape):
            raise fail(path, f"key {k!r} must be a pixel-grid field of shape {tuple(shape)}, got {np.shape(out[k])}")
    return out


def written_recovery_weight(d) -> float | None:
    """The adaptive recovery weight a result's strains were written with (its ``recovery_weight``; files of earlier
    versions, without ``recovery`` or with ``"average"``: 0, the nodal average); None where the contract's keys do
    not say (the result's own rule then decides)."""
    if d.get("recovery_weight") is not None:
        return float(d["recovery_weight"])
    return 0.0 if str(d.get("recovery", "average")) == "average" else None


def started_afresh(d) -> bool:
    """Whether a result file's increment started afresh (:func:`femreg.initial.previous_or_fresh`): its
    ``started_afresh``; files of earlier versions, without the key, said so in the message only."""
    if d.get("started_afresh") is not None:
        return bool(d["started_afresh"])
    return FRESH_NOTE in str(d.get("message", ""))


def read_result(path):
    """Read a result ``.npz`` (see the module docstring): ``(mesh, u, kwargs, element_grid)`` -- the skfem mesh, the
    nodal vector, the keyword arguments of :class:`femreg.RegistrationResult` (plus ``refined_from``, mm,
    ``auto_alpha``, a :class:`femreg.result_base.AutoAlpha`, and ``geometry``, the convex / sector mapping
    (:func:`beam_geometry`), when the file has them) and the element-strain grid
    (or None); :func:`femreg.load_result` builds the result from them.  Raises
    :class:`~femreg.errors.FileFormatError` naming the missing key or bad shape when the file is not a result.
    """
    from skfem import MeshQuad1

    d = _read(path)
    grid = {k: np.asarray(d[k], float) for k in GRID_FIELDS if k in d}
    grid = grid if len(grid) == len(GRID_FIELDS) else None
    element_grid = None
    if grid is not None and str(d.get("strain", "")) == "element":
        grid, element_grid = None, grid             # element strains: the default (recovered) grid is recomputed
    mesh = MeshQuad1(np.asarray(d["mesh_points"], float), np.asarray(d["mesh_cells"], np.int64))
    kw = dict(shape=tuple(int(n) for n in d["shape"]), spacing=d["spacing"],
              origin=d["origin"], regularizer=str(d.get("regularizer", "")), alpha=float(d.get("alpha", np.nan)),
              success=bool(d.get("success", False)), nit=int(d.get("nit", 0)), message=str(d.get("message", "")),
              energy_history=np.atleast_1d(d.get("energy_history", ())),
              ncc_before=float(d.get("ncc_before", np.nan)), ncc_after=float(d.get("ncc_after", np.nan)),
              grid=grid, quality=None if d.get("quality") is None else np.asarray(d["quality"], float),
              strategy=str(d.get("strategy", "")),
              excluded=None if d.get("excluded") is None else str(d["excluded"]), roi=d.get("roi"))
    if d.get("data_mask") is not None:
        kw["data_mask"] = np.asarray(d["data_mask"], bool)
    if d.get("refined_from") is not None:
        kw["refined_from"] = tuple(float(v) for v in np.ravel(d["refined_from"]))
    if d.get("slides") is not None:
        kw["slides"] = tuple(float(v) for v in np.ravel(d["slides"]))
    kw["recovery_weight"] = written_recovery_weight(d)
    if d.get("lambda_bar") is not None:
        kw["lambda_bar"] = float(d["lambda_bar"])
    kw["started_afresh"] = started_afresh(d)
    if d.get("auto_alpha") is not None:
        kw["auto_alpha"] = read_auto_alpha(d["auto_alpha"], path)
    geometry = beam_geometry(d)
    if geometry is not None:            # a convex / sector frame's result (femreg.geometry.BeamResult)
        kw["geometry"] = geometry
    return mesh, np.asarray(d["u"], float), kw, element_grid


def beam_geometry(d):
    """The convex / sector geometry of a result file's arrays ``d`` (the ``geometry_*`` keys a
    :class:`femreg.geometry.BeamResult` writes), or None for a linear array's result."""
    if "geometry_kind" not in d:
        return None
    from ..probes import as_geometry

    return as_geometry(dict(kind=str(d["geometry_kind"]), radius_mm=float(d["geometry_radius_mm"]),
                            angle_pitch_deg=float(d["geometry_angle_pitch_deg"])))


def save_result(path, result, **extra) -> Path:
    """Write a result (engine result object or dict) as compressed ``.npz`` with the contract keys it has plus
    ``extra`` arrays, atomically (a reader never sees a torn file).  ``.npz`` is appended to a path without it.

    The one writer of the contract (``RegistrationResult.save`` is this function)."""

    d = dict(as_result_dict(result), **extra)
    missing = [k for k in REQUIRED if k not in d]
    if missing:
        raise InputError(f"result lacks {', '.join(missing)}")
    check_mesh(d["mesh_points"], d["mesh_cells"], d["u"], where="result")
    data = {}
    for k, v in d.items():
        a = np.asarray(v)
        if a.dtype.kind == "O":
            raise InputError(f"result key {k!r} is not an array/number/string")
        data[k] = a
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    atomic_savez(path, **data)
    return path


def export_result(result, path, *, strains="both"):
    """Write a result (path / dict / object) as .vtu, .xdmf or .npz, chosen by ``path``'s extension."""
    d = as_result_dict(result)
    ext = Path(path).suffix.lower()
    if ext == ".npz":
        return save_result(path, d)
    writer = {".vtu": write_vtu, ".xdmf": write_xdmf}.get(ext)
    if writer is None:
        raise InputError(f"{path}: export format must be .vtu, .xdmf or .npz, not {ext!r}")
    return writer(path, d["mesh_points"], d["mesh_cells"], d["u"], strains=strains,
                  recovery_weight=written_recovery_weight(d))
