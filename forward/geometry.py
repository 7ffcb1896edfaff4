"""gmsh geometry of the paper's phantom, loaded into scikit-fem.

Coordinates (all mm): ``x`` = depth below the top face (axial, 0 at the top, positive downwards),
``y`` = lateral offset from the centre line, ``z`` (3D only) = elevational offset from the imaging plane.

2D (:func:`mesh_2d`): the central slice, block ``[0, B] x [-B/2, B/2]`` with a disk inclusion of diameter ``D``
centred at ``(d, 0)``.  Linear triangles (P2 fields are built on them by :mod:`forward.elasticity`).

3D (:func:`mesh_3d`): the block ``[0, B] x [-B/2, B/2]^2`` with a spherical inclusion centred at ``(d, 0, 0)``;
by default only the quarter ``y >= 0, z >= 0`` is meshed (two symmetry planes).  Linear tetrahedra.

Physical groups (loaded as ``mesh.subdomains`` / ``mesh.boundaries``):
subdomains ``"background"``, ``"inclusion"``; boundaries ``"bottom"`` (x = B), ``"patch"`` (compressed part of the
top face), ``"top_free"`` (rest of the top face; absent when the patch is the whole face), ``"sides"`` and, for
symmetric 3D models, ``"sym_y"`` (y = 0) and ``"sym_z"`` (z = 0).

gmsh is a process-global library: every function here initialises it, and finalises it in a ``finally`` block, so
gmsh is never left initialised (a session the caller opened is reused and left open).  Off the main thread it is initialised with ``interruptible=False`` (gmsh installs a
SIGINT handler, which Python only allows on the main thread).
"""
from __future__ import annotations

import contextlib
import threading

import numpy as np

__all__ = ["mesh_2d", "mesh_3d", "gmsh_session"]

_lock = threading.Lock()


@contextlib.contextmanager
def gmsh_session(verbose: bool = False):
    """Initialise gmsh for the duration of a ``with`` block and finalise it afterwards (serialised by a lock).

    If the caller already has gmsh initialised, that session is reused: a fresh model is added and removed
    again at the end, and gmsh is left initialised as it was found (never finalised under the caller's feet).
    """
    from femreg.optional import require

    gmsh = require("gmsh", feature="forward (gmsh meshes)")

    with _lock:
        owner = not gmsh.isInitialized()
        if owner:
            if threading.current_thread() is threading.main_thread():
                gmsh.initialize()
            else:  # gmsh's SIGINT handler can only be installed on the main thread
                gmsh.initialize(interruptible=False)
        try:
            old_terminal = gmsh.option.getNumber("General.Terminal")
            gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
            gmsh.option.setNumber("General.Verbosity", 2 if verbose else 0)
            yield gmsh
        finally:
            if owner:
                gmsh.finalize()
            else:
                try:
                    gmsh.model.remove()
                    gmsh.option.setNumber("General.Terminal", old_terminal)
                except Exception:  # pragma: no cover - best effort on a caller's session
                    pass


def _check_geometry(block_mm, inclusion_diameter_mm, inclusion_depth_mm, patch_mm, coarse_size_mm, mesh_size_mm):
    for name, val in [("block_mm", block_mm), ("inclusion_diameter_mm", inclusion_diameter_mm),
                      ("inclusion_depth_mm", inclusion_depth_mm), ("coarse_size_mm", coarse_size_mm),
                      ("mesh_size_mm", mesh_size_mm)]:
        if val is None or not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name} must be a positive finite number, got {val!r}")
    r = inclusion_diameter_mm / 2
    if inclusion_depth_mm - r <= 0 or inclusion_depth_mm + r >= block_mm or r >= block_mm / 2:
        raise ValueError(f"inclusion_depth_mm={inclusion_depth_mm} / inclusion_diameter_mm={inclusion_diameter_mm}: "
                         f"the inclusion must lie strictly inside the {block_mm} mm block")
    if patch_mm is not None:
        if not np.isfinite(patch_mm) or patch_mm <= 0 or patch_mm > block_mm:
            raise ValueError(f"patch_mm must be in (0, block_mm={block_mm}] or None, got {patch_mm!r}")


def _entities_in_box(gmsh, dim, box, eps=1e-6):
    x0, y0, z0, x1, y1, z1 = box
    return [t for _, t in gmsh.model.getEntitiesInBoundingBox(x0 - eps, y0 - eps, z0 - eps,
                                                               x1 + eps, y1 + eps, z1 + eps, dim)]


def _threshold(gmsh, in_field: int, size_min: float, size_max: float, dist_min: float, dist_max: float) -> int:
    """A gmsh Threshold size field: ``size_min`` within ``dist_min`` of ``in_field``, ``size_max`` beyond
    ``dist_max``."""
    th = gmsh.model.mesh.field.add("Threshold")
    for k, v in dict(InField=in_field, SizeMin=size_min, SizeMax=size_max, DistMin=dist_min, DistMax=dist_max).items():
        gmsh.model.mesh.field.setNumber(th, k, v)
    return th


def _generate(gmsh, fields, dim: int, algorithm: dict, coarse_size_mm: float) -> None:
    """Mesh with the minimum of the size ``fields`` as the only size source (boundary/point/curvature sizes off)."""
    mn = gmsh.model.mesh.field.add("Min")
    gmsh.model.mesh.field.setNumbers(mn, "FieldsList", fields)
    gmsh.model.mesh.field.setAsBackgroundMesh(mn)
    for k, v in {"Mesh.MeshSizeExtendFromBoundary": 0, "Mesh.MeshSizeFromPoints": 0,
                 "Mesh.MeshSizeFromCurvature": 0, "Mesh.MeshSizeMax": coarse_size_mm, **algorithm}.items():
        gmsh.option.setNumber(k, v)
    gmsh.model.mesh.generate(dim)


def _extract(gmsh, dim, elem_type, facet_type, groups_dom, groups_bnd):
    """Nodes, cells, per-name cell indices and per-name facet node lists from the current gmsh model."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = coords.reshape(-1, 3)[:, :dim]
    tag2row = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    tag2row[tags.astype(np.int64)] = np.arange(len(tags))
    nper = {2: 3, 4: 4}[elem_type]
    cells, subdomains, start = [], {}, 0
    for name, pg in groups_dom.items():
        blocks = []
        for ent in gmsh.model.getEntitiesForPhysicalGroup(dim, pg):
            _, ntags = gmsh.model.mesh.getElementsByType(elem_type, ent)
            blocks.append(tag2row[ntags.astype(np.int64)].reshape(-1, nper))
        c = np.vstack(blocks) if blocks else np.zeros((0, nper), dtype=np.int64)
        cells.append(c)
        subdomains[name] = np.arange(start, start + len(c))
        start += len(c)
    t = np.vstack(cells)
    used = np.unique(t)
    renum = np.full(len(tags), -1, dtype=np.int64)
    renum[used] = np.arange(len(used))
    t = renum[t]
    p = coords[used]
    nfper = {1: 2, 2: 3}[facet_type]
    facets = {}
    for name, pg in groups_bnd.items():
        blocks = []
        for ent in gmsh.model.getEntitiesForPhysicalGroup(dim - 1, pg):
            _, ntags = gmsh.model.mesh.getElementsByType(facet_type, ent)
            blocks.append(renum[tag2row[ntags.astype(np.int64)]].reshape(-1, nfper))
        facets[name] = np.vstack(blocks) if blocks else np.zeros((0, nfper), dtype=np.int64)
    return p, t, subdomains, facets


def _to_skfem(MeshCls, p, t, subdomains, facet_nodes):
    mesh = MeshCls(np.ascontiguousarray(p.T), np.ascontiguousarray(t.T))
    # skfem may reorder nodes of a cell (orientation) but keeps the cell order, so subdomains stay valid.
    # Match boundary facets by sorted node tuples.
    key_mesh = np.sort(mesh.facets, axis=0).T
    order = np.lexsort(key_mesh.T[::-1])
    sorted_keys = key_mesh[order]
    boundaries = {}
    for name, fn in facet_nodes.items():
        if len(fn) == 0:
            continue
        k = np.sort(fn, axis=1)
        # binary search on lexicographically sorted rows via a structured view
        dt = np.dtype([(f"f{i}", k.dtype) for i in range(k.shape[1])])
        a = np.ascontiguousarray(sorted_keys.astype(k.dtype)).view(dt).ravel()
        b = np.ascontiguousarray(k).view(dt).ravel()
        pos = np.searchsorted(a, b)
        pos = np.clip(pos, 0, len(a) - 1)
        ok = a[pos] == b
        if not np.all(ok):
            raise RuntimeError(f"boundary {name!r}: {np.sum(~ok)} facets not found in the mesh")
        boundaries[name] = np.sort(order[pos])
    return mesh.with_subdomains(subdomains).with_boundaries(boundaries)


def mesh_2d(*, block_mm: float = 160.0, inclusion_diameter_mm: float = 15.0, inclusion_depth_mm: float = 30.0,
            patch_mm: float | None = 50.0, coarse_size_mm: float = 8.0, mesh_size_mm: float = 1.0,
            fine_region_mm: tuple[float, float] | None = (80.0, 30.0), verbose: bool = False):
    """Triangle mesh of the central slice (2D models).

    Parameters
    ----------
    block_mm : float
        Side of the square block, mm (paper: 160).
    inclusion_diameter_mm, inclusion_depth_mm : float
        Diameter of the circular inclusion and depth of its centre below the top face, mm (paper: 15, 30).
    patch_mm : float or None
        Width of the compression patch centred on the top face, mm; ``None`` = whole top face.
    coarse_size_mm : float
        Element size far from the imaged area, mm.
    mesh_size_mm : float
        Element size in the refined region (imaged area and inclusion), mm.
    fine_region_mm : (depth, half_width) or None
        Refined box ``[0, depth] x [-half_width, half_width]``; ``None``: only the inclusion and patch edges refined.

    Returns
    -------
    skfem.MeshTri1
        ``p[0]`` = depth x, ``p[1]`` = lateral y (mm), with subdomains and boundaries as in the module docstring.
    """
    from skfem import MeshTri1

    _check_geometry(block_mm, inclusion_diameter_mm, inclusion_depth_mm, patch_mm, coarse_size_mm, mesh_size_mm)
    B, r, d = float(block_mm), inclusion_diameter_mm / 2.0, float(inclusion_depth_mm)
    half = B / 2
    w = half if patch_mm is None else min(patch_mm / 2.0, half)
    with gmsh_session(verbose) as gmsh:
        occ = gmsh.model.occ
        gmsh.model.add("slice2d")
        rect = occ.addRectangle(0, -half, 0, B, B)
        disk = occ.addDisk(d, 0, 0, r, r)
        occ.fragment([(2, rect)], [(2, disk)])
        if w < half:  # split the top edge at the patch ends
            pts = [occ.addPoint(0, -w, 0), occ.addPoint(0, w, 0)]
            occ.fragment(occ.getEntities(2), [(0, q) for q in pts])
        occ.synchronize()
        eps = 1e-6
        inc = _entities_in_box(gmsh, 2, (d - r, -r, 0, d + r, r, 0))
        allsurf = [t for _, t in gmsh.model.getEntities(2)]
        bg = [s for s in allsurf if s not in inc]
        pg = {"background": gmsh.model.addPhysicalGroup(2, bg), "inclusion": gmsh.model.addPhysicalGroup(2, inc)}
        bottom = _entities_in_box(gmsh, 1, (B, -half, 0, B, half, 0))
        top = _entities_in_box(gmsh, 1, (0, -half, 0, 0, half, 0))
        patch = _entities_in_box(gmsh, 1, (0, -w, 0, 0, w, 0))
        top_free = [c for c in top if c not in patch]
        sides = (_entities_in_box(gmsh, 1, (0, -half, 0, B, -half, 0))
                 + _entities_in_box(gmsh, 1, (0, half, 0, B, half, 0)))
        pb = {"bottom": gmsh.model.addPhysicalGroup(1, bottom), "patch": gmsh.model.addPhysicalGroup(1, patch),
              "sides": gmsh.model.addPhysicalGroup(1, sides)}
        if top_free:
            pb["top_free"] = gmsh.model.addPhysicalGroup(1, top_free)
        # size fields: fine in the imaged box and near the inclusion / patch edges, coarse elsewhere
        fields = []
        if fine_region_mm is not None:
            fb = gmsh.model.mesh.field.add("Box")
            fd, fw = fine_region_mm
            for k, v in dict(VIn=mesh_size_mm, VOut=coarse_size_mm, XMin=-eps, XMax=min(fd, B), YMin=-min(fw, half),
                             YMax=min(fw, half), ZMin=-1, ZMax=1, Thickness=max(fd, 2 * fw) * 0.5).items():
                gmsh.model.mesh.field.setNumber(fb, k, v)
            fields.append(fb)
        curves_near = _entities_in_box(gmsh, 1, (d - r, -r, 0, d + r, r, 0))
        dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(dist, "CurvesList", curves_near)
        if w < half:
            pts = _entities_in_box(gmsh, 0, (0, -w, 0, 0, -w, 0)) + _entities_in_box(gmsh, 0, (0, w, 0, 0, w, 0))
            gmsh.model.mesh.field.setNumbers(dist, "PointsList", pts)
        fields.append(_threshold(gmsh, dist, mesh_size_mm, coarse_size_mm, 2 * mesh_size_mm,
                                 max(30.0, 10 * mesh_size_mm)))
        _generate(gmsh, fields, 2, {"Mesh.Algorithm": 6}, coarse_size_mm)
        p, t, sub, fac = _extract(gmsh, 2, 2, 1, pg, pb)
    return _to_skfem(MeshTri1, p, t, sub, fac)


def mesh_3d(*, block_mm: float = 160.0, inclusion_diameter_mm: float = 15.0, inclusion_depth_mm: float = 30.0,
            patch_mm: float | None = 50.0, coarse_size_mm: float = 16.0, mesh_size_mm: float = 2.0,
            fine_region_mm: tuple[float, float, float] | None = (80.0, 30.0, 3.0), symmetry: str = "quarter",
            verbose: bool = False):
    """Tetrahedral mesh of the 3D block (quarter, half or full model).

    Parameters
    ----------
    block_mm, inclusion_diameter_mm, inclusion_depth_mm, patch_mm
        As in :func:`mesh_2d`; the patch is the ``patch_mm x patch_mm`` square centred on the top face.
    coarse_size_mm, mesh_size_mm : float
        Coarse element size and element size in the refined region (imaging plane, inclusion), mm.
    fine_region_mm : (depth, half_width, half_thickness) or None
        Refined slab ``[0, depth] x [-hw, hw] x [-ht, ht]`` around the imaging plane z = 0.
    symmetry : {"quarter", "half", "full"}
        ``"quarter"``: y >= 0, z >= 0 (boundaries ``sym_y``, ``sym_z``); ``"half"``: z >= 0 (``sym_z``);
        ``"full"``: the whole block.

    Returns
    -------
    skfem.MeshTet1
        ``p[0]`` = depth x, ``p[1]`` = lateral y, ``p[2]`` = elevation z (mm).
    """
    from skfem import MeshTet1

    _check_geometry(block_mm, inclusion_diameter_mm, inclusion_depth_mm, patch_mm, coarse_size_mm, mesh_size_mm)
    if symmetry not in ("quarter", "half", "full"):
        raise ValueError(f"symmetry must be 'quarter', 'half' or 'full', got {symmetry!r}")
    B, r, d = float(block_mm), inclusion_diameter_mm / 2.0, float(inclusion_depth_mm)
    half = B / 2
    w = half if patch_mm is None else min(patch_mm / 2.0, half)
    y0 = 0.0 if symmetry == "quarter" else -half
    z0 = 0.0 if symmetry in ("quarter", "half") else -half
    eps = 1e-6
    with gmsh_session(verbose) as gmsh:
        occ = gmsh.model.occ
        gmsh.model.add("block3d")
        box = occ.addBox(0, y0, z0, B, half - y0, half - z0)
        sph = occ.addSphere(d, 0, 0, r)
        tools = [(3, sph)]
        if w < half:
            # a thin rectangle on the top face (x = 0) marks the patch; build in xy plane then rotate to x = 0
            py0, pz0 = max(-w, y0), max(-w, z0)
            rect = occ.addRectangle(py0, pz0, 0, w - py0, w - pz0)  # in (y, z) after the rotation below
            # rectangle lies in plane z=0 with coords (X, Y); map X->y, Y->z, plane -> x = 0
            occ.rotate([(2, rect)], 0, 0, 0, 1, 1, 1, 2 * np.pi / 3)  # cyclic permutation (X,Y,Z)->(Y,Z,X)
            tools.append((2, rect))
        out, _ = occ.fragment([(3, box)], tools)
        occ.synchronize()
        # drop anything of the sphere outside the box (quarter/half models cut it)
        vols = [t for _, t in gmsh.model.getEntities(3)]
        inside_box = _entities_in_box(gmsh, 3, (0, y0, z0, B, half, half))
        extra = [v for v in vols if v not in inside_box]
        if extra:
            occ.remove([(3, v) for v in extra], recursive=True)
            occ.synchronize()
        # surfaces left dangling (rectangle outside etc.)
        vols = [t for _, t in gmsh.model.getEntities(3)]
        inc = _entities_in_box(gmsh, 3, (d - r, -r, -r, d + r, r, r))
        bg = [v for v in vols if v not in inc]
        pg = {"background": gmsh.model.addPhysicalGroup(3, bg), "inclusion": gmsh.model.addPhysicalGroup(3, inc)}
        bottom = _entities_in_box(gmsh, 2, (B, y0, z0, B, half, half))
        top = _entities_in_box(gmsh, 2, (0, y0, z0, 0, half, half))
        patch = _entities_in_box(gmsh, 2, (0, max(-w, y0), max(-w, z0), 0, w, w))
        top_free = [s for s in top if s not in patch]
        sides = []
        for bb in [(0, half, z0, B, half, half), (0, y0, half, B, half, half)]:
            sides += _entities_in_box(gmsh, 2, bb)
        sym_y, sym_z = [], []
        if y0 == 0.0:
            sym_y = _entities_in_box(gmsh, 2, (0, 0, z0, B, 0, half))
        else:
            sides += _entities_in_box(gmsh, 2, (0, y0, z0, B, y0, half))
        if z0 == 0.0:
            sym_z = _entities_in_box(gmsh, 2, (0, y0, 0, B, half, 0))
        else:
            sides += _entities_in_box(gmsh, 2, (0, y0, z0, B, half, z0))
        pb = {"bottom": gmsh.model.addPhysicalGroup(2, bottom), "patch": gmsh.model.addPhysicalGroup(2, patch),
              "sides": gmsh.model.addPhysicalGroup(2, sides)}
        for name, ents in [("top_free", top_free), ("sym_y", sym_y), ("sym_z", sym_z)]:
            if ents:
                pb[name] = gmsh.model.addPhysicalGroup(2, ents)
        fields = []
        if fine_region_mm is not None:
            fd, fw, ft = fine_region_mm
            fb = gmsh.model.mesh.field.add("Box")
            for k, v in dict(VIn=mesh_size_mm, VOut=coarse_size_mm, XMin=-eps, XMax=min(fd, B),
                             YMin=max(-fw, y0) - eps, YMax=min(fw, half), ZMin=max(-ft, z0) - eps, ZMax=min(ft, half),
                             Thickness=max(fd, fw) * 0.6).items():
                gmsh.model.mesh.field.setNumber(fb, k, v)
            fields.append(fb)
        dist = gmsh.model.mesh.field.add("Distance")
        sph_surf = [s for s in _entities_in_box(gmsh, 2, (d - r, -r, -r, d + r, r, r))
                    if s not in sym_y + sym_z]
        gmsh.model.mesh.field.setNumbers(dist, "SurfacesList", sph_surf)
        gmsh.model.mesh.field.setNumber(dist, "Sampling", 40)
        fields.append(_threshold(gmsh, dist, mesh_size_mm, coarse_size_mm, mesh_size_mm,
                                 max(20.0, 8 * mesh_size_mm)))
        if w < half:  # patch edges: stress singularity
            dpe = gmsh.model.mesh.field.add("Distance")
            pc = [c for c in _entities_in_box(gmsh, 1, (0, max(-w, y0), max(-w, z0), 0, w, w))]
            gmsh.model.mesh.field.setNumbers(dpe, "CurvesList", pc)
            gmsh.model.mesh.field.setNumber(dpe, "Sampling", 50)
            fields.append(_threshold(gmsh, dpe, 1.5 * mesh_size_mm, coarse_size_mm, mesh_size_mm,
                                     max(20.0, 8 * mesh_size_mm)))
        _generate(gmsh, fields, 3, {"Mesh.Algorithm3D": 10}, coarse_size_mm)
        p, t, sub, fac = _extract(gmsh, 3, 4, 2, pg, pb)
    return _to_skfem(MeshTet1, p, t, sub, fac)
