"""Adaptive refinement of volume registration (``register_volume(..., refine=...)``): the 3D form of
:mod:`femreg.refine`, whose marking, budget and splitting code it uses.

After the solve on the hexahedral tensor mesh, the jump of the momentum tensor
``A[u] = lambda_bar div(u) I + 2 sym grad(u)`` (eq:meq, ``lambda_bar`` :data:`JUMP_LAMBDA_BAR_3D`, the momentum
regularisers' value on volumes) across every interior face, ``|[[A]] n|`` from the element-centre strains
(:func:`face_jumps`): what the momentum TV of eq:dmreg2 penalises on hexahedra.  A face normal to the axial axis
marks the two x-slabs (element layers) beside it, a lateral face the y-slabs, an elevational face the z-slabs;
the cut and the budget are :mod:`femreg.refine`'s (:func:`femreg.refine.jump_cut`,
:func:`femreg.refine.slabs_within_budget`: the slabs that stand out most first, at most ``max_growth`` times
the unrefined mesh's elements).  The marked slabs are halved (``levels`` times) on voxel-cell boundaries
(:func:`femreg.refine.refined_axes`), so the refined mesh is again a tensor mesh whose faces lie on voxel-cell
boundaries: the voxel grid, the separable Hessian and the face jumps of the regulariser work on it unchanged,
and it holds the coarse trilinear field exactly (nested meshes, :func:`transfer_3d`).  One Gauss-Newton step on
the refined mesh from the transferred solution follows (:attr:`femreg.refine.Refinement.maxiter`), with the
regulariser's weight of eq:objf that of the unrefined mesh (:func:`femreg.scaling.refined_alpha`).  The image
term's reference values and gradients at the voxels are shared with the unrefined solve (the voxel block is the
same, :meth:`femreg.voxels.VoxelSSDTerm.on_mesh`).  The slip region and the local relaxation of 2D are not
used on volumes.

``Refinement(interior=True)`` (:func:`mark_volume`) also marks a slab by the variation inside it: the whole
tensor's face jump ``|[[A]]|`` and the second difference of the element-centre A[u] along the slab's axis
(:func:`interior_variation`).  A slab on a plane of symmetry of the field (the elevational slab across an
inclusion's central plane) shows no jump ``[[A]] n`` at its faces, the largest second difference.

``Refinement(plane=z0)`` leaves the elevational slabs to the plane of interest z = z0 mm: none is marked by the
field, the slab across the plane is cut to the one voxel cell around it (:func:`plane_breaks`), and the budget
goes to the x- and y-slabs.  ``Refinement(even=True)`` cuts a marked slab into equal pieces down to ``min_size``
(:func:`even_axes`) where halving stops above it.  :data:`PLANE_REFINEMENT` combines them with the interior
marking for the in-plane strain of the imaging plane z = 0 (the paper's 3D phantom: docs/study_report.md).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from skfem import MeshHex1

from .errors import InputError, pass_as
from .refine import (DEFAULT, Refinement, RefinementRecord, finish_passes, jump_cut, marked_slabs, refine_name,
                     refined_axes, slab_scores, slabs_within_budget, strong_levels)
from .regularizers.momentum import LAMBDA_BAR_3D
from .volume_fields import HexLocator, element_strain_operator_3d
from .voxels import tensor_axes_3d

__all__ = ["VOLUME_REFINEMENT", "PLANE_REFINEMENT", "JUMP_LAMBDA_BAR_3D", "as_volume_refinement", "face_jumps",
           "interior_variation", "mark_volume", "plane_breaks", "even_axes", "refine_hex_mesh", "transfer_3d",
           "refine_volume_passes"]

#: lambda_bar of the 3D "jump" indicator's A[u]: the momentum regularisers' value on volumes.
JUMP_LAMBDA_BAR_3D = LAMBDA_BAR_3D

#: ``refine="auto"`` on volumes: one pass, marked slabs halved twice (2 mm -> 0.5 mm where the jumps stand out,
#: one solve), at most 3x the unrefined mesh's elements; the smallest slabs 0.5 mm axially, 0.6 mm laterally,
#: 1 mm elevationally (and never below 2 voxels).
VOLUME_REFINEMENT = Refinement(passes=1, levels=2, max_growth=3.0, min_size=(0.5, 0.6, 1.0), relax=None)

#: The in-plane strain of the imaging plane z = 0: :data:`VOLUME_REFINEMENT` with the interior marking
#: (:attr:`femreg.refine.Refinement.interior`), the elevational slab across z = 0 cut to one voxel cell and the
#: other z-slabs left (:attr:`femreg.refine.Refinement.plane`), marked slabs cut into equal pieces down to
#: 0.5 x 0.6 mm (:attr:`femreg.refine.Refinement.even`; those under 3.5x the cut once,
#: :attr:`femreg.refine.Refinement.strong`), at most 8x the unrefined mesh's elements.  Measured on the paper's
#: 3D phantom with ``element_size=(2, 2.4, 2)`` (lateral slabs of 8 voxel cells of 0.3 mm, which cut into four
#: 0.6 mm ones; femreg's default 2.1 / 1.8 mm slabs leave 0.9 mm pieces): in-plane total strain error on the
#: central plane 5.99 % (floor 4.41 %), 39072 hexahedra, 6.0 GB (on the default 2 mm base mesh 6.09 %);
#: docs/study_report.md (volume study).
PLANE_REFINEMENT = dataclasses.replace(VOLUME_REFINEMENT, interior=True, even=True, strong=3.5, max_growth=8.0,
                                       plane=0.0)


def as_volume_refinement(spec) -> Refinement | None:
    """``refine=`` of :func:`femreg.volume.register_volume`: None / False / 0 / "default" -> None (off); "auto" ->
    :data:`VOLUME_REFINEMENT`; an int N -> it with N passes; a :class:`femreg.refine.Refinement` as it is (the
    "jump" indicator only; ``slip`` and ``relax`` are not used on volumes; a two-value ``min_size`` takes the
    lateral one elevationally)."""
    spec = refine_name(spec)
    if spec is None or spec is False or (isinstance(spec, str) and spec in (DEFAULT, "none", "off")):
        return None
    if isinstance(spec, str):
        if spec == "slip":
            raise InputError("refine='slip' (the slip region of a shear band) is 2D only; volumes take None, an "
                             "integer number of passes, 'auto' or a Refinement")
        if spec != "auto":
            raise InputError(f"refine must be None, an integer number of passes, 'auto', 'none' or a Refinement, "
                             f"got {spec!r}")
        return VOLUME_REFINEMENT
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        return dataclasses.replace(VOLUME_REFINEMENT, passes=int(spec)) if spec else None
    if isinstance(spec, Refinement):
        if spec.indicator != "jump":
            raise InputError(f"volumes refine with the 'jump' indicator only, got {spec.indicator!r}")
        if spec.slip is not None:
            raise InputError("the slip region of refinement is not available on volumes ("
                             + pass_as("slip=None", "--refine auto or a number of passes") + ")")
        return spec if spec.passes > 0 else None
    raise InputError(f"refine must be None, an integer number of passes, 'auto' or a Refinement, got {spec!r}")


def _min_size_3d(opts: Refinement) -> tuple:
    ms = tuple(opts.min_size)
    return ms if len(ms) == 3 else (ms[0], ms[1], ms[1])


def _need_hex_tensor(mesh):
    ta = tensor_axes_3d(mesh)
    if ta is None:
        raise InputError("volume refinement needs an axis-aligned tensor hexahedral mesh (femreg.voxels.roi_mesh_3d)")
    return ta


def _momentum_3d(e, lambda_bar: float) -> np.ndarray:
    """A[u] (n_el, 3, 3) from element-centre strains (n_el, 6) in (exx, eyy, ezz, exy, exz, eyz) order."""
    A = np.empty((e.shape[0], 3, 3))
    div = e[:, 0] + e[:, 1] + e[:, 2]
    for a, b, c in ((0, 0, 0), (1, 1, 1), (2, 2, 2), (0, 1, 3), (0, 2, 4), (1, 2, 5)):
        A[:, a, b] = A[:, b, a] = 2.0 * e[:, c]
    for a in range(3):
        A[:, a, a] += lambda_bar * div
    return A


def _centre_momentum(mesh, u, lambda_bar):
    """A[u] of the element centres on the cell grid (E_x, E_y, E_z, 3, 3) and its RMS Frobenius norm."""
    _need_hex_tensor(mesh)
    cell = HexLocator(mesh).cell
    e = (element_strain_operator_3d(mesh) @ np.asarray(u, float)).reshape(6, -1).T
    A = _momentum_3d(e, lambda_bar)
    return A[cell], float(np.sqrt(np.mean(np.sum(A ** 2, axis=(1, 2)))))


def face_jumps(mesh, u, lambda_bar: float = JUMP_LAMBDA_BAR_3D, whole: bool = False):
    """``(jumps, scale)``: ``jumps[a]`` the ``|[[A]] n|`` across the interior faces normal to axis a of a tensor
    hexahedral mesh, on the cell grid with axis a one shorter (between slabs i and i + 1), from the element-centre
    strains (``whole``: the whole tensor's jump ``|[[A]]|``, Frobenius); ``scale`` the RMS over the elements of
    ``|A[u]|`` (Frobenius).  Dimensionless (strain units)."""
    G, scale = _centre_momentum(mesh, u, lambda_bar)          # (E_x, E_y, E_z, 3, 3)
    if whole:
        return [np.linalg.norm(np.diff(G, axis=a), axis=(-2, -1)) for a in range(3)], scale
    return [np.linalg.norm(np.diff(G[..., :, a], axis=a), axis=-1) for a in range(3)], scale     # [[A]] e_a


def interior_variation(mesh, u, lambda_bar: float = JUMP_LAMBDA_BAR_3D):
    """``(second, scale)``: ``second[a]`` the second difference of the element-centre A[u] along axis a,
    ``|A_{i-1} - 2 A_i + A_{i+1}|`` (Frobenius), on the cell grid (0 on the first and last slab of each axis);
    ``scale`` as :func:`face_jumps`.  Dimensionless.  A slab on a plane of symmetry of the field, where the
    strain is extremal along that axis, has equal centre values on both sides (the jumps ``[[A]] n`` of its two
    faces are small by symmetry) and the largest second difference."""
    G, scale = _centre_momentum(mesh, u, lambda_bar)
    out = []
    for a in range(3):
        g = np.moveaxis(G, a, 0)
        d = np.zeros(g.shape[:-2])
        d[1:-1] = np.linalg.norm(g[2:] - 2.0 * g[1:-1] + g[:-2], axis=(-2, -1))
        out.append(np.moveaxis(d, 0, a))
    return out, scale


def mark_volume(mesh, u, opts: Refinement):
    """``(marked, scores)``: per axis the slabs of a tensor hexahedral mesh to split (boolean) and each slab's
    largest face jump over the cut (marked where > 1), :mod:`femreg.refine`'s rule on :func:`face_jumps`.
    With ``opts.interior`` the score is the larger of the whole tensor's face jump (:func:`face_jumps`,
    ``whole=True``) and the slab's largest second difference (:func:`interior_variation`), each over its own cut
    (:func:`femreg.refine.jump_cut`)."""
    if not opts.interior:
        jumps, scale = face_jumps(mesh, u)
        return marked_slabs(slab_scores(jumps), jump_cut(jumps, opts, scale), opts)
    jumps, scale = face_jumps(mesh, u, whole=True)
    second, _ = interior_variation(mesh, u)
    cut_j, cut_s = jump_cut(jumps, opts, scale), jump_cut(second, opts, scale)
    with np.errstate(invalid="ignore", divide="ignore"):
        sc = [np.maximum(j / cut_j, np.moveaxis(d, a, 0).reshape(d.shape[a], -1).max(axis=1) / cut_s)
              for a, (j, d) in enumerate(zip(slab_scores(jumps), second))]
    return marked_slabs(sc, 1.0, opts)


def plane_breaks(breaks, plane: float, spacing: float, origin: float) -> np.ndarray:
    """Elevational breaks (mm, on voxel-cell boundaries ``origin + (k - 1/2) spacing``) with the slab holding
    ``plane`` (mm) cut at the two boundaries of the voxel cell around the voxel plane nearest it: a slab one
    voxel cell thick centred on that voxel plane (the recovered strain there then comes from element centres
    ``spacing`` apart across it; the one slab allowed below ``min_size`` and two voxel cells).  Breaks already
    there are kept; ``breaks`` unchanged when both are.  A plane
    outside ``breaks``' span is an :class:`~femreg.errors.InputError`."""
    b = np.asarray(breaks, float)
    if not (b[0] <= plane <= b[-1]):
        raise InputError(f"refinement plane {plane} mm is outside the mesh's elevational span "
                         f"{b[0]:.3f}..{b[-1]:.3f} mm")
    k = np.rint((plane - origin) / spacing)
    new = [c for c in (origin + (k - 0.5) * spacing, origin + (k + 0.5) * spacing)
           if b[0] + 0.5 * spacing < c < b[-1] - 0.5 * spacing and np.min(np.abs(b - c)) > 0.5 * spacing]
    return np.sort(np.concatenate([b, new])) if new else b


def even_axes(breaks, marked, spacing, origin, min_size, levels):
    """``(new_breaks, splits)`` per axis, as :func:`femreg.refine.refined_axes` takes its arguments: each marked
    slab cut into the most pieces of (nearly) equal voxel-cell counts, none below ``min_size[a]`` mm or 2 voxel
    cells, at most ``2 ** levels`` pieces (an integer array ``marked``: ``2 ** marked[i]``).  Halving stops
    above the smallest size where a half has an odd count of cells (a 6-cell slab of 0.3 mm cells: two 0.9 mm
    halves, which cannot be halved into 2-cell pieces); this cuts it into three 0.6 mm slabs.  Breaks on
    voxel-cell boundaries, so the refined mesh is nested in the coarse one."""
    out, counts = [], []
    for b, m, o, h, ms in zip(breaks, marked, origin, spacing, min_size):
        b = np.asarray(b, float)
        m = np.asarray(m)
        lev = m.astype(np.int64) * int(levels) if m.dtype == bool else np.asarray(m, np.int64)
        k = np.rint((b - o) / h + 0.5).astype(np.int64)              # voxel-cell boundary indices
        min_cells = max(2, int(np.ceil(ms / h * (1 - 1e-9))))
        new = []
        for i in np.flatnonzero(lev > 0):
            n = int(k[i + 1] - k[i])
            pieces = min(2 ** int(lev[i]), n // min_cells)
            if pieces >= 2:
                new.extend(k[i] + np.rint(np.arange(1, pieces) * n / pieces).astype(np.int64))
        kk = np.union1d(k, new)
        out.append(o + (kk - 0.5) * h if new else b)
        counts.append(int(kk.size - k.size))
    return out, counts


def refine_hex_mesh(mesh, marked, spacing, origin, min_size=(0.5, 0.6, 1.0), levels: int = 1, split=None):
    """The tensor hexahedral mesh with the ``marked`` slabs (per axis) of ``mesh`` halved ``levels`` times, breaks
    on voxel-cell boundaries.  Returns ``(mesh, splits per axis)``; the same mesh object when nothing was split."""

    axes, _ = _need_hex_tensor(mesh)
    for a in range(3):
        if np.shape(marked[a]) != (axes[a].size - 1,):
            raise InputError(f"marked slabs along axis {a} must be ({axes[a].size - 1},), got {np.shape(marked[a])}")
    new, counts = (split or refined_axes)(axes, marked, spacing, origin, min_size, levels)
    if not any(counts):
        return mesh, counts
    return MeshHex1.init_tensor(*new), counts


def transfer_3d(u, mesh, new_mesh) -> np.ndarray:
    """Nodal vector of ``new_mesh`` holding the trilinear field ``u`` of ``mesh`` (exact for nested tensor
    meshes)."""
    loc = HexLocator(mesh)
    inside, _, X, nodes = loc.locate(new_mesh.p.T)
    if not np.all(inside):
        raise InputError("refined mesh has nodes outside the mesh it refines")
    W = np.stack([(X[0] if i else 1 - X[0]) * (X[1] if j else 1 - X[1]) * (X[2] if k else 1 - X[2])
                  for i in (0, 1) for j in (0, 1) for k in (0, 1)])          # (8, n), the order of locate's nodes
    u = np.asarray(u, float)
    out = np.empty(3 * new_mesh.p.shape[1])
    for c in range(3):
        out[c::3] = np.sum(W * u[c::3][nodes], axis=0)
    return out


def refine_volume_passes(sol, opts: Refinement, solve_on, spacing, origin):
    """Up to ``opts.passes`` times: mark (:func:`mark_volume`), keep within the budget, refine
    (:func:`refine_hex_mesh`) and solve again with ``solve_on(mesh, u_start)`` from the previous solution carried
    over (:func:`transfer_3d`).  ``sol``: the first solve (:class:`femreg.volume.VolumeSolve`).  Stops when nothing
    is split (or a later pass adds fewer than ``opts.min_added`` of the elements).  Returns
    ``(sol, RefinementRecord)``; a pass's ``rows``, ``columns``, ``slices`` are the x-, y-, z-slabs added."""
    axes, _ = _need_hex_tensor(sol.mesh)
    base_size = tuple(float(np.median(np.diff(a))) for a in axes)
    ms = _min_size_3d(opts)
    budget = np.inf if opts.max_growth is None else opts.max_growth * sol.mesh.t.shape[1]
    base_gn, nit, record = sol.gn, int(sol.gn.nit), []
    split = even_axes if opts.even else None
    for k in range(opts.passes):
        t = time.perf_counter()
        mesh = sol.mesh
        axes, _ = tensor_axes_3d(mesh)
        marked, score = mark_volume(mesh, sol.u, opts)
        marked = list(strong_levels(marked, score, opts.strong, opts.levels))
        zb = axes[2]
        if opts.plane is not None:          # the elevational axis goes to the plane of interest alone
            marked[2] = np.zeros_like(marked[2])
            zb = plane_breaks(axes[2], float(opts.plane), float(spacing[2]), float(origin[2]))
        if np.isfinite(budget):             # the budget of the x- and y-slabs after the plane's cut
            marked = slabs_within_budget(axes, marked, score, spacing, origin, ms, opts.levels,
                                         budget * (axes[2].size - 1) / (zb.size - 1), split=split)
        new, counts = refine_hex_mesh(mesh, marked, spacing, origin, ms, opts.levels, split=split)
        if zb.size > axes[2].size:
            new_axes = tensor_axes_3d(new)[0]
            new = MeshHex1.init_tensor(new_axes[0], new_axes[1], zb)
            counts = [counts[0], counts[1], int(zb.size - axes[2].size)]
        if new is mesh or (k > 0 and new.t.shape[1] < (1 + opts.min_added) * mesh.t.shape[1]):
            break
        sol = solve_on(new, transfer_3d(sol.u, mesh, new))
        nit += int(sol.gn.nit)
        record.append(dict(elements=int(mesh.t.shape[1]), elements_after=int(new.t.shape[1]), rows=int(counts[0]),
                           columns=int(counts[1]), slices=int(counts[2]), nit=int(sol.gn.nit),
                           seconds=time.perf_counter() - t))
    finish_passes(sol, record, opts, base_gn, nit)
    return sol, RefinementRecord(record, base_size)
