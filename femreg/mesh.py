"""Meshes for the displacement field: a structured bilinear-quad mesh over the region of interest (ROI), or a
user's quad mesh (scikit-fem ``MeshQuad1``, or any file meshio/gmsh can read).

The default structured mesh (:func:`roi_mesh`) covers the image minus a margin.  Its outer boundary and every
element edge lie on pixel-cell boundaries (half-way between pixel centres), so every pixel centre lies strictly
inside exactly one element, the pixel midpoint rule of the image term integrates each element's area exactly
(summed pixel weights = mesh area), and pixel location is pure arithmetic (:mod:`femreg.pixels`).

Default element size
--------------------
``DEFAULT_ELEMENT_SIZE = (2.0, 2.0)`` mm (axial, lateral): about 104 axial samples x 7 scan lines per element,
36 x 22 elements (1.6 k nodes) on the paper's 72 x 44 mm image, 7 elements across its 15 mm inclusion.  On the
synthetic paper-geometry pair (benchmarks/bench_register.py --study; SNR 12 dB, 0.4-0.8 % compression) the
best total strain error over alpha (always at alpha ~ 30 for R_eps) was 28.4 / 21.7 / 19.2 / 17.7 % with
1 / 1.5 / 2 / 3 mm elements (axial strain error 15 / 9.9 / 5.5 / 2.8 %): with speckle at 12 dB, small elements
see too few samples and the strain is noise dominated (0.5 mm was worse still).  The synthetic field is smooth
(a 6 mm Gaussian bump), so it rewards coarse meshes monotonically; 2 mm is the compromise that keeps 7
elements across the paper's 15 mm inclusion (3 mm would leave 5).  Pass ``element_size`` for other data.
"""
from __future__ import annotations


import numpy as np
from skfem import MeshQuad1

from .errors import InputError, pass_as

__all__ = ["DEFAULT_ELEMENT_SIZE", "DEFAULT_MARGIN", "roi_mesh", "as_quad_mesh", "check_mesh_in_image",
           "tensor_structure", "mesh_stamp", "check_mesh"]

#: Default element size (axial, lateral) in mm.
DEFAULT_ELEMENT_SIZE = (2.0, 2.0)
#: Default ROI margin (axial, lateral) in mm, removed from every side of the image.  It keeps x + u inside the
#: image for displacements up to about the margin (0.8 % of 72 mm is 0.6 mm axially).
DEFAULT_MARGIN = (1.0, 1.0)


def _breaks(n_pix: int, lo_pix: int, hi_pix: int, size_pix: float) -> np.ndarray:
    """Element edges, in pixel-edge indices, spanning pixel cells [lo_pix, hi_pix) with about size_pix each."""
    n_cells = hi_pix - lo_pix
    n_el = max(1, int(round(n_cells / size_pix)))
    return np.unique(np.round(np.linspace(lo_pix, hi_pix, n_el + 1)).astype(int))


def check_element_size(element_size, spacing, mesh=None) -> None:
    """InputError for a given element size below one pixel along both axes (mm; a size in metres, 0.0015 for 1.5
    mm): the mesh would take one pixel per element, about a thousand times the elements meant, and the solve
    would not end in useful time."""
    if element_size is None or mesh is not None:
        return
    h = np.broadcast_to(np.asarray(element_size, float), (2,))
    sp = np.broadcast_to(np.asarray(spacing, float).ravel()[:2], (2,))
    if np.all(np.isfinite(h)) and np.all(h > 0) and np.all(h < sp):
        text = " ".join(f"{v:g}" for v in np.ravel(element_size))
        mm = " ".join(f"{v * 1e3:g}" for v in np.ravel(element_size))
        metres = pass_as(f"element_size={mm} (CLI: --element-size {mm})", f"--element-size {mm}")
        raise InputError(pass_as(f"element_size {text} mm", f"--element-size {text} (mm)")
                         + f" is smaller than a pixel ({sp[0]:g} x {sp[1]:g} mm, axial x lateral): element sizes "
                           f"are in mm" + (f"; read as metres it is {metres}" if np.all(h * 1e3 >= sp) else ""))


def roi_mesh(shape, spacing, origin=(0.0, 0.0), *, element_size=None, margin=None) -> MeshQuad1:
    """Structured bilinear-quad mesh over the image minus a margin.

    Parameters
    ----------
    shape : (n_axial, n_lateral)
        Image shape in pixels.
    spacing, origin : (2,) mm
        Pixel spacing and the centre of pixel [0, 0].
    element_size : float or (2,) mm, optional
        Target element size (axial, lateral); rounded to a whole number of pixels and adjusted so that the
        elements tile the ROI.  Default :data:`DEFAULT_ELEMENT_SIZE`.
    margin : float or (2,) mm, optional
        Strip removed on every side of the image.  Default :data:`DEFAULT_MARGIN`.

    Returns
    -------
    skfem.MeshQuad1
        ``mesh.p[0]`` axial x (mm), ``mesh.p[1]`` lateral y (mm); edges on pixel-cell boundaries.
    """
    spacing = np.asarray(spacing, dtype=float)
    origin = np.asarray(origin, dtype=float)
    h = np.broadcast_to(np.asarray(DEFAULT_ELEMENT_SIZE if element_size is None else element_size, float), (2,))
    m = np.broadcast_to(np.asarray(DEFAULT_MARGIN if margin is None else margin, float), (2,))
    if np.any(~np.isfinite(h)) or np.any(h <= 0):
        raise InputError(f"element_size must be > 0 mm, got {tuple(float(v) for v in h)}")
    if np.any(~np.isfinite(m)) or np.any(m < 0):
        raise InputError(f"margin must be >= 0 mm, got {tuple(float(v) for v in m)}")
    axes = []
    for a in range(2):
        n = int(shape[a])
        lo = int(np.ceil(m[a] / spacing[a] - 1e-9))
        hi = n - lo
        if hi - lo < 1:
            size = ", ".join(f"{k * d:.4g}" for k, d in zip(shape, spacing))
            raise InputError(f"margin {m[a]} mm leaves no pixels along axis {a} (image {n} pixels of "
                             f"{spacing[a]} mm; the image is ({size}) mm (axial, lateral): a spacing in "
                             f"centimetres or metres must be given in mm, or pass a smaller margin)")
        b = _breaks(n, lo, hi, max(1.0, h[a] / spacing[a]))
        # Pixel-edge index k sits at the centre of pixel k minus half a pixel.
        axes.append(origin[a] + (b - 0.5) * spacing[a])
    return MeshQuad1.init_tensor(axes[0], axes[1])


def as_quad_mesh(mesh) -> MeshQuad1:
    """Accept a ``skfem.MeshQuad1``, a path to a mesh file (gmsh .msh, or anything meshio reads), or a
    ``meshio.Mesh`` with quad cells; return a ``MeshQuad1`` in mm with p[0] = axial x, p[1] = lateral y."""
    if isinstance(mesh, MeshQuad1):
        return mesh
    try:
        import meshio
    except ImportError:  # pragma: no cover
        meshio = None
    if isinstance(mesh, (str, bytes)) or hasattr(mesh, "__fspath__"):
        import os
        path = os.fspath(mesh)
        if not os.path.exists(path):
            raise InputError(f"mesh file not found: {path}")
        if meshio is None:  # skfem reads mesh files with meshio
            from .optional import require
            require("meshio", feature="reading a mesh file")
        try:
            return MeshQuad1.load(path)
        except Exception as exc:  # noqa: BLE001 - report any reader failure as bad input
            raise InputError(f"cannot read a quad mesh from {path}: {exc}") from None
    if meshio is not None and isinstance(mesh, meshio.Mesh):
        quads = [c.data for c in mesh.cells if c.type == "quad"]
        if not quads:
            raise InputError("meshio mesh has no 'quad' cells; femreg needs bilinear quadrilaterals")
        return MeshQuad1(np.asarray(mesh.points[:, :2], float).T, np.vstack(quads).T)
    if hasattr(mesh, "p") and hasattr(mesh, "t"):
        raise InputError(f"mesh must be a quadrilateral skfem.MeshQuad1, got {type(mesh).__name__}")
    raise InputError(f"mesh must be a skfem.MeshQuad1, a meshio.Mesh or a mesh file path, got {type(mesh).__name__}")


def check_mesh_in_image(mesh: MeshQuad1, shape, spacing, origin) -> None:
    """Raise :class:`InputError` unless every node lies inside the image's pixel cells."""
    lo = np.asarray(origin, float) - 0.5 * np.asarray(spacing, float)
    hi = lo + np.asarray(shape, float) * np.asarray(spacing, float)
    tol = 1e-9 * np.asarray(spacing, float)
    out = np.any((mesh.p.T < lo[None] - tol) | (mesh.p.T > hi[None] + tol), axis=1)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise InputError(f"mesh outside the image: {int(out.sum())} of {mesh.p.shape[1]} nodes lie outside "
                         f"[{lo[0]:g}, {hi[0]:g}] x [{lo[1]:g}, {hi[1]:g}] mm (first node {k} at "
                         f"{tuple(np.round(mesh.p[:, k], 6))})")


def tensor_node_grid(mesh: MeshQuad1, xs, ys) -> np.ndarray:
    """``(n_x, n_y)`` index of the node at every position of a tensor mesh's node grid (``xs``, ``ys`` from
    :func:`tensor_structure`): axial i, lateral j."""
    G = np.empty((np.size(xs), np.size(ys)), dtype=np.int64)
    G[np.searchsorted(xs, mesh.p[0]), np.searchsorted(ys, mesh.p[1])] = np.arange(mesh.p.shape[1])
    return G


def tensor_structure(mesh: MeshQuad1):
    """If ``mesh`` is an axis-aligned tensor-product grid, return ``(xs, ys, cell)`` with the sorted axial and
    lateral node coordinates and ``cell[i, j]`` = element index of the cell [xs[i], xs[i+1]] x [ys[j], ys[j+1]];
    otherwise None.  Lets point location be arithmetic (searchsorted) instead of a search.

    Built once per mesh object and kept on it (a registration asks about its two meshes about ten times, ~1 ms
    each on 3000 nodes), with a stamp of its node and element arrays, so a mesh changed in place is looked at
    again; the arrays are read-only (shared by every caller)."""
    stamp = mesh_stamp(mesh)
    hit = getattr(mesh, _TENSOR_ATTR, None)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    out = _tensor_structure(mesh)
    if out is not None:
        for a in out:
            a.flags.writeable = False     # shared by every caller
    try:
        setattr(mesh, _TENSOR_ATTR, (stamp, out))
    except (AttributeError, TypeError):   # pragma: no cover - a mesh type that takes no attributes: not kept
        pass
    return out


def mesh_stamp(mesh) -> tuple:
    """A cheap stamp of a mesh's node and element arrays (address, shape, sums): what is kept on a mesh object
    (:func:`tensor_structure`, :func:`femreg.fields.element_strain_operator`) is built again when it changes."""
    return (mesh.p.ctypes.data, mesh.p.shape, float(np.sum(mesh.p)), int(np.sum(mesh.t)))


#: Attribute of a mesh holding its :func:`tensor_structure` (with the stamp it was built for).
_TENSOR_ATTR = "_femreg_tensor_structure"


def _tensor_structure(mesh: MeshQuad1):
    p, t = mesh.p, mesh.t
    xs, ys = np.unique(p[0]), np.unique(p[1])
    if xs.size * ys.size != p.shape[1] or (xs.size - 1) * (ys.size - 1) != t.shape[1]:
        return None
    corners = p[:, t]                          # (2, 4, n_el)
    x0, x1 = corners[0].min(0), corners[0].max(0)
    y0, y1 = corners[1].min(0), corners[1].max(0)
    i = np.searchsorted(xs, x0)
    j = np.searchsorted(ys, y0)
    if np.any(i + 1 >= xs.size) or np.any(j + 1 >= ys.size):
        return None
    if not (np.allclose(xs[i + 1], x1) and np.allclose(ys[j + 1], y1)):
        return None
    # every corner must be at (x0|x1, y0|y1)
    okx = np.isclose(corners[0], x0) | np.isclose(corners[0], x1)
    oky = np.isclose(corners[1], y0) | np.isclose(corners[1], y1)
    if not (okx.all() and oky.all()):
        return None
    cell = -np.ones((xs.size - 1, ys.size - 1), dtype=np.int64)
    cell[i, j] = np.arange(t.shape[1])
    if (cell < 0).any():
        return None
    return xs, ys, cell


def check_mesh(points, cells, u=None, where="mesh"):
    """Validate (2, n_nodes) points, (4, n_el) cells and (2*n_nodes,) u; return float/int arrays."""
    try:
        p = np.asarray(points, dtype=float)
        t = np.asarray(cells)
    except (TypeError, ValueError):
        raise InputError(f"{where}: mesh_points / mesh_cells are not numeric arrays") from None
    if p.ndim != 2 or p.shape[0] != 2 or p.shape[1] < 4:
        raise InputError(f"{where}: mesh_points must be (2, n_nodes) with n_nodes >= 4, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError(f"{where}: mesh_points contain NaN/Inf")
    if t.ndim != 2 or t.shape[0] != 4 or t.shape[1] < 1 or t.dtype.kind not in "iu":
        raise InputError(f"{where}: mesh_cells must be (4, n_el) integers, got {t.shape} {t.dtype}")
    if t.min() < 0 or t.max() >= p.shape[1]:
        raise InputError(f"{where}: mesh_cells index nodes outside 0..{p.shape[1] - 1}")
    t = t.astype(np.int64)
    if u is None:
        return p, t, None
    uu = np.asarray(u, dtype=float)
    n = p.shape[1]
    if uu.shape == (n, 2):
        uu = uu.ravel()
    if uu.shape != (2 * n,):
        raise InputError(f"{where}: u must be (2*n_nodes,) = ({2 * n},) interleaved [ux0, uy0, ...], got {uu.shape}")
    if not np.all(np.isfinite(uu)):
        raise InputError(f"{where}: u contains NaN/Inf")
    return p, t, uu
