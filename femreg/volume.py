"""Registration of RF volumes (axial, lateral, elevational) = (x, y, z): :func:`register_volume` and
:func:`track_volume`, which :func:`femreg.register` and :func:`femreg.track` call for 3D arrays.

The same method as in 2D, one dimension up: eq:objf = psi (eq:IR) + R on trilinear hexahedra
(:func:`femreg.voxels.roi_mesh_3d`), the image term integrated at voxel centres with tricubic B-spline warps of
the moving volume and the fixed reference gradient of eq:wfnew (:class:`femreg.voxels.VoxelSSDTerm`); the
regularisers are the 2D ones, whose weak forms are written for any dimension (R_eps, R_eps_i; the momentum TV
with the jumps of A n across interior faces, A = lambda_bar div(u) I + 2 sym grad u, lambda_bar
:data:`femreg.regularizers.momentum.LAMBDA_BAR_3D` with the dilatation at the element centre, and hourglass
control of the hexahedra); alpha is rescaled by element volume (:mod:`femreg.scaling`); Gauss-Newton
(:func:`femreg.solver.gauss_newton`, linear solver :class:`femreg.linsolve.SPDSolver`).

Stages: validate -> normalise (each volume minus its mean, over its spread: :func:`femreg.image.normalize_pair`) -> mesh -> initial guess (coarse to fine: a global search
over axial strain and translation on decimated envelope volumes, then Gauss-Newton on the envelopes with a mesh
twice as coarse, :func:`coarse_to_fine`) -> prefilter (the splines, and the image term's reference values and
gradients, after which the reference volume is released) -> Gauss-Newton on the RF -> peak-hopping check
and repair (nodes whose u_x is a whole RF period off their neighbourhood's median are reseeded and the solve is
repeated, kept only if the energy falls) -> check (never worse than the start; NCC floor; elements whose envelope
matches better one RF period off, :func:`hop_check`) -> :class:`VolumeResult`.
"""
from __future__ import annotations

import contextvars
import copy
import functools
import json
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from . import orientation
from .autoalpha import ImageTerm, choose_alpha, register_auto
from .echo_volume import crop_for_volume, registered_crop_volume, route_volume, unmatched_crop_volume
from .errors import InputError, counted
from .image import normalize_pair, require_spacing
from .regularizers import Regularizer, available_regularizers
from .repair import (HOP_FRACTION, MAX_HOPPED_FRACTION, MAX_POOR_FRACTION, MIN_NCC, envelope_lag_ncc_3d,
                     frame_flag, hop_note, hopped_fraction, lag_gain, mark_tainted, own_flag, retry_flagged)
from .scaling import effective_alpha
from .linsolve import SPDSolver
from .solver import GN_STRAIN_TOL, GN_STRAIN_TOL_TIGHT, Objective, gauss_newton, single_blas_thread
from .speckle import envelope
from .strategy import component_tol, effective_regularizer_options, fresh_regularizer
from .volume_fields import HexLocator, element_strain_operator_3d
from .refine import DEFAULT as DEFAULT_REFINE, default_refine
from .volume_refine import as_volume_refinement, refine_volume_passes, transfer_3d
from .volume_result import VolumeResult
from .voxels import (DEFAULT_ELEMENT_SIZE_3D, SplineVolume, VoxelGrid, VoxelSSDTerm, roi_mesh_3d, tensor_axes_3d,
                     validate_spacing_3d, validate_volume)

__all__ = ["register_volume", "track_volume", "volumes_to", "coarse_to_fine", "global_search_3d", "VolumeTrack",
           "GLOBAL_STRAINS_3D", "hop_check", "voxel_image_term", "noise_at_depth_volume"]

#: Axial strains tried by the global search (-8 % to +4 %, steps of 0.5 %).
GLOBAL_STRAINS_3D = tuple(np.round(np.arange(-0.08, 0.04 + 1e-9, 0.005), 4))
#: Largest translation the global search considers, as a fraction of the volume extent per axis.
SEARCH_FRACTION_3D = 0.10


# ----------------------------------------------------------------------------------------------------------
# Initial guess
# ----------------------------------------------------------------------------------------------------------

#: Voxels per pass of the column-wise volume transforms (envelope, RF period): their complex spectra and
#: filtered copies then take ~50 MB instead of several times the volume.
COLUMN_CHUNK_3D = 1 << 22


def _column_chunks(volume):
    """``(flat, slices)``: the volume as (n_x, n_y n_z) columns and slices of about :data:`COLUMN_CHUNK_3D`
    voxels over them."""
    nx = volume.shape[0]
    flat = volume.reshape(nx, -1)
    step = max(1, COLUMN_CHUNK_3D // nx)
    return flat, [slice(a, a + step) for a in range(0, flat.shape[1], step)]


def _envelope_3d(volume, q: int = 1) -> np.ndarray:
    """Envelope |analytic signal| along the axial direction of a volume (each (y, z) line), decimated axially by
    ``q`` (:func:`_decimate`); computed a block of lines at a time (each line is independent, so the values are
    those of the whole volume at once)."""
    flat, chunks = _column_chunks(volume)
    out = None
    for c in chunks:
        e = _decimate(envelope(np.asarray(flat[:, c], float)), q)
        if out is None:
            out = np.empty((e.shape[0], flat.shape[1]))
        out[:, c] = e
    return out.reshape((out.shape[0],) + volume.shape[1:])


def _rf_period_3d(volume, spacing) -> float:
    """:func:`femreg.speckle.rf_period` of the volume's axial lines, a block of lines at a time."""
    from scipy import fft as sfft

    from .speckle import _centroid_period

    flat, chunks = _column_chunks(volume)
    nf = sfft.next_fast_len(flat.shape[0], real=True)
    P = 0.0
    for c in chunks:
        P = P + np.sum(np.abs(sfft.rfft(np.asarray(flat[:, c], float), n=nf, axis=0)) ** 2, axis=1)
    return _centroid_period(P / flat.shape[1], nf, float(spacing[0]))


def _decimate(env, q: int) -> np.ndarray:
    """Axial Gaussian low-pass (sigma q / 2 samples) and every q-th sample."""
    if q <= 1:
        return env
    return ndimage.gaussian_filter1d(env, q / 2.0, axis=0, mode="nearest")[::q]


def global_search_3d(ref_env, mov_env, spacing, origin, strains=GLOBAL_STRAINS_3D,
                     fraction: float = SEARCH_FRACTION_3D):
    """Best axial strain s and translation t (3,) mm of ``u(x) = (s (x - x_c), 0, 0) + t`` between two envelope
    volumes: for each s the moving envelope is resampled axially and cross-correlated with the reference by FFT
    (translations up to ``fraction`` of the extent, sub-voxel by a parabola through the peak); the pair with the
    largest normalised correlation wins.  The strains are scanned at twice their step first, then the two
    neighbours of the best.  Returns ``(s, t, x_c, ncc)``."""
    from scipy import fft as sfft

    a = ref_env - ref_env.mean()
    shape = a.shape
    x = origin[0] + spacing[0] * np.arange(shape[0])
    xc = float(x.mean())
    lim = [max(1, int(fraction * n)) for n in shape]
    full = [sfft.next_fast_len(n + L + 1, real=True) for n, L in zip(shape, lim)]
    Fa = np.conj(sfft.rfftn(a, s=full, axes=(0, 1, 2)))
    na = float(np.linalg.norm(a))
    keep = []
    for ax, L in enumerate(lim):        # lags within the search range (negative lags wrap around)
        k = np.zeros(full[ax], bool)
        k[:L + 1] = True
        k[full[ax] - L:] = True
        keep.append(k)
    mask = keep[0][:, None, None] & keep[1][None, :, None] & keep[2][None, None, :]
    grid_yz = np.meshgrid(np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
    cache = {}

    def score(s):
        if s in cache:
            return cache[s]
        pos = (xc + (1.0 + s) * (x - xc) - origin[0]) / spacing[0]          # where mov is read for x
        # axial resampling only: linear interpolation along x of every (y, z) line
        i0 = np.clip(np.floor(pos).astype(int), 0, shape[0] - 2)
        f = np.clip(pos - i0, 0.0, 1.0)[:, None, None]
        m = (1.0 - f) * mov_env[i0] + f * mov_env[i0 + 1]
        m = m - m.mean()
        nm = float(np.linalg.norm(m))
        if not (na > 0 and nm > 0):
            cache[s] = (-np.inf, np.zeros(3))
            return cache[s]
        c = sfft.irfftn(Fa * sfft.rfftn(m, s=full, axes=(0, 1, 2)), s=full, axes=(0, 1, 2))
        c[~mask] = -np.inf
        k = np.unravel_index(int(np.argmax(c)), c.shape)
        t = np.empty(3)
        for ax in range(3):
            n2 = c.shape[ax]
            km, kp = list(k), list(k)
            km[ax] = (k[ax] - 1) % n2
            kp[ax] = (k[ax] + 1) % n2
            c0, cm, cp = c[k], c[tuple(km)], c[tuple(kp)]
            den = cm - 2 * c0 + cp
            off = 0.5 * (cm - cp) / den if np.isfinite(den) and den < 0 else 0.0
            lag = k[ax] if k[ax] <= n2 // 2 else k[ax] - n2
            t[ax] = (lag + float(np.clip(off, -0.5, 0.5))) * spacing[ax]
        cache[s] = (float(c[k]) / (na * nm), t)
        return cache[s]

    del grid_yz
    strains = list(strains)
    coarse = strains[::2]
    best = max(coarse, key=lambda s: score(s)[0])
    i = strains.index(best)
    for j in (i - 1, i + 1):
        if 0 <= j < len(strains):
            score(strains[j])
    s = max(cache, key=lambda v: cache[v][0])
    return float(s), cache[s][1], xc, cache[s][0]


def _nodal(fn, mesh) -> np.ndarray:
    """Interleaved nodal vector of a field callable(points (n, 3)) -> (n, 3) on ``mesh``."""
    return np.asarray(fn(mesh.p.T), float).reshape(-1)


def coarse_to_fine(ref, mov, spacing, origin, mesh, reg_factory, *, maxiter=20, tol=1e-3, linear_solver="auto",
                   at=None):
    """The initial guess on ``mesh``: global search (:func:`global_search_3d`) on envelope volumes decimated
    axially to about half the lateral spacing, then Gauss-Newton on the (undecimated axially low-passed)
    envelopes on a mesh twice as coarse from that affine field; the coarse field at ``mesh``'s nodes, or at the
    points ``at`` (n_nodes, 3) mm (a sequence increment: the nodes moved by S of eq:IR).
    Returns ``(u0, info)``."""
    t0 = time.perf_counter()
    q = max(1, int(round(0.5 * min(spacing[1], spacing[2]) / spacing[0])))
    dr, dm = _envelope_3d(ref, q), _envelope_3d(mov, q)
    sp_d = np.array([spacing[0] * q, spacing[1], spacing[2]])
    s, t, xc, g_ncc = global_search_3d(dr, dm, sp_d, origin)
    t_global = time.perf_counter() - t0

    def affine(pts):
        out = np.tile(t, (len(pts), 1))
        out[:, 0] += s * (pts[:, 0] - xc)
        return out

    # envelope level: Gauss-Newton on the envelopes (no carrier: its basin is a speckle cell, not a quarter
    # period), decimated volumes on a mesh twice as coarse
    t1 = time.perf_counter()
    (ax, ay, az), _ = tensor_axes_3d(mesh)
    h = np.array([np.mean(np.diff(a)) for a in (ax, ay, az)]) * 2.0
    lo = np.array([ax[0], ay[0], az[0]])
    hi = np.array([ax[-1], ay[-1], az[-1]])
    from skfem import MeshHex1

    n_fine = [a.size - 1 for a in (ax, ay, az)]
    axes = [np.linspace(lo[a], hi[a], max(min(2, n_fine[a]), int(round((hi[a] - lo[a]) / h[a]))) + 1)
            for a in range(3)]
    coarse = MeshHex1.init_tensor(*axes)
    er = dr / np.sqrt(np.mean(dr ** 2))
    em = dm / np.sqrt(np.mean(dm ** 2))
    orig_d = np.asarray(origin, float)
    E1, E2 = SplineVolume(er, sp_d, orig_d), SplineVolume(em, sp_d, orig_d)
    u_c = _nodal(affine, coarse)
    info = {"global_strain": s, "global_translation": t, "global_ncc": g_ncc, "decimation": q}
    try:
        sol = solve_volume(E1, E2, coarse, er.shape, sp_d, orig_d, reg_factory, u_c, maxiter=maxiter, tol=tol,
                           linear_solver=linear_solver, mask_outside=True)
        u_c = sol.u
        info["envelope_nit"] = sol.gn.nit
    except InputError:
        pass
    loc = HexLocator(coarse)
    pts = mesh.p.T if at is None else np.asarray(at, float)
    u0 = np.column_stack([v for k, v in loc.sample(u_c, pts).items() if k in ("ux", "uy", "uz")]).ravel()
    u0 = np.nan_to_num(u0)
    info["timings"] = {"global_search": t_global, "envelope_level": time.perf_counter() - t1}
    return u0, info


# ----------------------------------------------------------------------------------------------------------
# Solve, repair, check
# ----------------------------------------------------------------------------------------------------------

@dataclass
class VolumeSolve:
    mesh: object
    u: np.ndarray
    gn: object
    data: VoxelSSDTerm
    reg: Regularizer
    start: np.ndarray
    psi_start: float


def solve_volume(I1, I2, mesh, shape, spacing, origin, reg_factory, u0, *, offset=None, maxiter=20, tol=1e-3,
                 linear_solver="auto", callback=None, mask_outside=False, strain_tol=None, data=None) -> VolumeSolve:
    """One Gauss-Newton solve of eq:objf on a hexahedral ``mesh`` (the 3D form of :func:`femreg.gnsolve.solve`):
    voxel SSD term with the fixed reference gradient + a fresh regulariser with alpha per 2 x 2 x 2 mm element.
    ``offset``: S at the voxels of the mesh block (n, 3) mm or None.  ``mask_outside``: voxels that ``u0`` maps
    out of the moving volume get weight 0.  ``data``: the :class:`VoxelSSDTerm` of an earlier solve on the same
    mesh, volumes and offset, whose reference values and gradients are shared (not recomputed nor copied)."""
    if data is None:
        data = VoxelSSDTerm(VoxelGrid(mesh, shape, spacing, origin), I1, I2, offset=offset)
    else:
        data = data.fresh()
    if mask_outside:
        out = data.outside_mask(u0)
        if out.any() and not out.all():
            data.w = np.where(out, 0.0, data.w0)
    reg = reg_factory()
    reg.alpha = effective_alpha(reg.alpha, mesh)
    reg.setup(mesh)
    psi_start = data.energy(u0)
    # the band of a hexahedral mesh grows with its cross-section squared: large systems to PARDISO if installed
    solver = SPDSolver(linear_solver, large_method="pardiso") if linear_solver in ("auto", "pardiso") else \
        linear_solver
    gn = gauss_newton(Objective(data, reg), u0, maxiter=maxiter, tol=tol, linear_solver=solver,
                      callback=callback, strain_tol=strain_tol,
                      strain_operator=None if strain_tol is None else element_strain_operator_3d(mesh))
    return VolumeSolve(mesh=mesh, u=gn.x, gn=gn, data=data, reg=reg, start=u0, psi_start=psi_start)


def hop_nodes_3d(mesh, ux, period: float) -> np.ndarray:
    """Whole RF periods (int per node) by which u_x differs from the median of its 3 x 3 x 3 node neighbourhood,
    where that difference exceeds :data:`femreg.repair.HOP_FRACTION` of the period (else 0)."""
    axes, node = tensor_axes_3d(mesh)
    U = ux[node]
    med = ndimage.median_filter(U, size=3, mode="nearest")
    d = U - med
    k = np.where(np.abs(d) > HOP_FRACTION * period, np.round(d / period), 0).astype(int)
    out = np.zeros(mesh.p.shape[1], int)
    out[node.ravel()] = k.ravel()
    return out


def hop_check(data, warped, period: float):
    """Peak hopping seen in the volumes themselves, as in 2D (:func:`femreg.repair.hop_gain`): per element the
    gain in envelope match of u_x shifted by one RF period (:func:`femreg.repair.envelope_lag_ncc_3d`,
    :func:`femreg.repair.lag_gain`); more than :data:`femreg.repair.MAX_HOPPED_FRACTION` of the elements above
    :data:`femreg.repair.HOP_GAIN` fail the result.  ``data``: the :class:`femreg.voxels.VoxelSSDTerm`;
    ``warped``: I_2(x + S + u) at its voxels; ``period``: RF period, mm.  Returns ``(gain (n_elements,), notes)``,
    ``notes`` empty when the result passes."""
    gain = lag_gain(envelope_lag_ncc_3d(data, warped, period))
    hopped = hopped_fraction(gain)
    return gain, ([hop_note(hopped, period)] if hopped > MAX_HOPPED_FRACTION else [])


def _repair(sol, resolve, mesh, period):
    """Reseed nodes whole periods off their neighbourhood (:func:`hop_nodes_3d`) and solve again; keep the new
    solve if it lowers the energy.  Returns ``(sol, hops, notes)``."""
    k = hop_nodes_3d(mesh, sol.u[0::3], period)
    if not k.any():
        return sol, k, []
    u = sol.u.copy()
    u[0::3] -= k * period
    new = resolve(u)
    if new.gn.fun < sol.gn.fun:
        left = hop_nodes_3d(mesh, new.u[0::3], period)
        note = f"peak hopping repaired at {counted(int(np.count_nonzero(k)), 'node')}"
        if left.any():
            note += f" ({int(np.count_nonzero(left))} still off)"
        return new, left, [note]
    n = int(np.count_nonzero(k))
    return sol, k, [f"{counted(n, 'node')} look{'s' if n == 1 else ''} a period off "
                    f"their neighbourhood; reseeding them did not lower the energy (kept)"]


# ----------------------------------------------------------------------------------------------------------
# register / track
# ----------------------------------------------------------------------------------------------------------

def _validate(reference, moving, spacing, origin, regularizer, strategy, maxiter, tol):
    ref = validate_volume(reference, "reference volume")
    mov = validate_volume(moving, "moving volume")
    if ref.shape != mov.shape:
        raise InputError(f"volume shape mismatch: reference {ref.shape} vs moving {mov.shape}")
    spacing, origin = validate_spacing_3d(spacing, origin)
    if strategy not in ("auto", "paper"):
        raise InputError(f"strategy must be 'auto' (or 'paper', treated as 'auto' on volumes), got {strategy!r}")
    if not isinstance(regularizer, (str, Regularizer)):
        raise InputError(f"regularizer must be a name or a Regularizer, got {type(regularizer).__name__}")
    if isinstance(regularizer, str) and regularizer not in available_regularizers():
        raise InputError(f"unknown regularizer {regularizer!r}; choose one of {available_regularizers()}")
    if int(maxiter) < 0 or not (np.isfinite(tol) and tol > 0):
        raise InputError(f"need maxiter >= 0 and tol > 0, got maxiter={maxiter}, tol={tol}")
    return ref, mov, spacing, origin


def _voxel_offset(offset, grid: VoxelGrid) -> np.ndarray:
    """S of eq:IR at the voxels of ``grid``'s block, (n_voxels, 3) mm, from a VolumeResult, a callable or a
    nodal vector on ``grid.mesh``."""
    if isinstance(offset, VolumeResult):
        return np.nan_to_num(offset.displacement(grid.points()))
    s_nodes = _start(offset, grid.mesh, "offset")
    return np.column_stack([grid.expand(U).ravel() for U in grid.nodal_grid(s_nodes)])


def _offset_nodes(offset, mesh) -> np.ndarray:
    """S of eq:IR at ``mesh``'s nodes, (3 n_nodes,) mm, from a VolumeResult, a callable or a nodal vector."""
    if isinstance(offset, VolumeResult):
        return np.nan_to_num(offset.displacement(mesh.p.T)).ravel()
    return _start(offset, mesh, "offset")


def voxel_image_term(reference_image, moving_image, mesh, register_kwargs) -> ImageTerm:
    """The :class:`femreg.autoalpha.ImageTerm` of a volume pair on ``mesh``, built as :func:`register_volume`
    builds its image term (normalised volumes, tricubic splines, the offset S at the voxels): what
    ``alpha="auto"`` reads on volumes (the ``image_term`` of :func:`femreg.autoalpha.choose_alpha`)."""
    spacing, origin = validate_spacing_3d(register_kwargs["spacing"], register_kwargs.get("origin", (0.0, 0.0, 0.0)))
    ref = validate_volume(reference_image, "reference volume")
    mov = validate_volume(moving_image, "moving volume")
    if register_kwargs.get("normalize", True):
        ref, mov, _ = normalize_pair(ref, mov)
    grid = VoxelGrid(mesh, ref.shape, spacing, origin)
    offset = register_kwargs.get("offset")
    S = None if offset is None else _voxel_offset(offset, grid)
    data = VoxelSSDTerm(grid, SplineVolume(ref, spacing, origin), SplineVolume(mov, spacing, origin), offset=S)
    return ImageTerm(data=data, n_samples=grid.n_voxels, residual_image=data.residual,
                     gradients=tuple(np.asarray(g, float) for g in data.g))


def _start(initial, mesh, what="initial"):
    """Nodal start (3 n_nodes,) from a VolumeResult, a callable(points (n, 3)) -> (n, 3) or a nodal vector."""
    n = mesh.p.shape[1]
    if isinstance(initial, VolumeResult):
        return np.nan_to_num(initial.displacement(mesh.p.T)).ravel()
    if callable(initial):
        v = np.asarray(initial(mesh.p.T.copy()), float)
        if v.shape != (n, 3):
            raise InputError(f"{what} callable must return shape ({n}, 3), got {v.shape}")
        arr = v.ravel()
    else:
        arr = np.asarray(initial, float).ravel()
        if arr.size != 3 * n:
            raise InputError(f"{what} nodal vector must have 3 * n_nodes = {3 * n} entries, got {arr.size}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} contains NaN/Inf values")
    return arr.copy()


@single_blas_thread
def _single_element_axes(mesh) -> list:
    """Names of the axes along which a tensor hexahedral mesh has a single element."""
    names = ("axial", "lateral", "elevational")
    return [names[a] for a in range(3) if len(np.unique(np.round(mesh.p[a], 9))) <= 2]


def _default_refine(refine, args, geometry=None):
    """``refine=`` of :func:`register_volume` with its default resolved by :func:`femreg.refine.default_refine`
    (the 2D rule: "auto" for ``strategy="auto"`` R_P_sigma on the default mesh, with no offset, a numeric alpha and
    no geometry; off otherwise).  ``args``: the registration's keywords (missing ones count as their defaults)."""
    return default_refine(refine, strategy=args.get("strategy", "auto"),
                          regularizer=args.get("regularizer", "momentum-stress"), mesh=args.get("mesh"),
                          element_size=args.get("element_size"), offset=args.get("offset"), geometry=geometry,
                          alpha=args.get("alpha"))


def _refine(sol, opts, u0, I2, shape, spacing, origin, reg_factory, kw):
    """The refinement stage of :func:`register_volume` (:func:`femreg.volume_refine.refine_volume_passes`):
    each pass one :func:`solve_volume` on the refined mesh, its image term the unrefined one's on the same voxels
    (:meth:`femreg.voxels.VoxelSSDTerm.on_mesh`), the regulariser's weight of eq:objf the unrefined mesh's
    (:func:`femreg.scaling.refined_alpha`).  Returns ``(sol, u0, hops)`` on the final mesh, ``sol.refinement``
    the record."""
    from .scaling import refined_alpha

    base, base_data = sol.mesh, sol.data
    base_data._cache = (None, None)     # its last residual (a volume-sized array) is not needed beside the refined one

    def solve_on(m, u_start):
        def factory():
            r = reg_factory()
            r.alpha = refined_alpha(r.alpha, base, m)
            return r
        rkw = kw if opts.maxiter is None else dict(kw, maxiter=min(opts.maxiter, kw["maxiter"]))
        return solve_volume(None, I2, m, shape, spacing, origin, factory, u_start, data=base_data.on_mesh(m), **rkw)

    sol, record = refine_volume_passes(sol, opts, solve_on, spacing, origin)
    hops = np.zeros(sol.mesh.p.shape[1], int)
    if sol.mesh is not base:            # the start on the refined mesh, for the check "never worse than the start"
        u0 = transfer_3d(u0, base, sol.mesh)
        sol.psi_start = sol.data.energy(u0)
    sol.refinement = record
    return sol, u0, hops


def _check(sol, u0, hops, notes, period) -> dict:
    """The check stage of :func:`register_volume` on the solve ``sol`` (its mesh, from the start ``u0``, with the
    nodes ``hops`` still off after the repair and the ``notes`` so far): the result's ``u``, ``success``,
    ``message``, ``notes``, ``quality``, ``ncc_before``, ``ncc_after``, ``hop_gain``."""
    notes = list(notes)
    mesh = sol.mesh
    data = sol.data
    data._cache = (None, None)          # the last residual (a volume-sized array) is not needed by the checks
    ncc_before = data.ncc(None)
    u = sol.u
    # as in 2D (femreg.repair.check_result) the checks below decide, not the solver's own stop: a line search
    # that cannot decrease the energy further returns the best iterate, a result like any other
    success = bool(np.all(np.isfinite(u)))
    if not success:
        u = u0
        notes.append("the solve produced non-finite values; returning the initial guess")
    E_start = sol.psi_start + sol.reg.energy(u0)
    if not sol.gn.fun <= E_start:
        u, success = u0, False
        notes.append("the result explains the volumes less than its start (start returned)")
    b = data.warped_moving(u)           # one warp for the element NCCs, the NCC and the hop check
    quality = data.element_ncc(u, warped=b)
    ncc_after = data.ncc(u, warped=b)
    t_hop = time.process_time()
    hop_gain, hop_notes = hop_check(data, b, period)
    hop_cpu = time.process_time() - t_hop
    del b
    poor = float(np.mean(quality[np.isfinite(quality)] < MIN_NCC)) if np.isfinite(quality).any() else 1.0
    if ncc_after < MIN_NCC:
        success = False
        notes.append(f"the volumes do not match (NCC after {ncc_after:.2f} < {MIN_NCC})")
    elif poor > MAX_POOR_FRACTION:
        success = False
        notes.append(f"{poor:.0%} of the elements match below NCC {MIN_NCC}")
    if hops.any():
        success = False
        notes.append(f"peak hopping at {counted(int(np.count_nonzero(hops)), 'node')} could not be repaired")
    if hop_notes:
        success = False
        notes += hop_notes
    thin = _single_element_axes(mesh)
    if thin:
        # one element across an axis: its normal strain is that element's alone, unchecked by any neighbour
        # (measured: ezz 1.8 % for 0.5 % true on a 4 mm thick volume, 105 % total strain error)
        success = False
        notes.append(f"only one element across the {' and '.join(thin)} extent: the strains along it are not "
                     "measured; give a thicker volume or a smaller element_size")
    message = "; ".join([sol.gn.message] + notes) if notes else sol.gn.message
    if not success:
        message = f"FAILED: {'; '.join(notes) or sol.gn.message} (Gauss-Newton stopped after {sol.gn.nit} iterations)"
    return dict(u=u, success=success, message=message, notes=notes, quality=quality, ncc_before=ncc_before,
                ncc_after=ncc_after, hop_gain=hop_gain, hop_check_cpu=hop_cpu)


def register_volume(reference_image, moving_image, *, spacing, origin=(0.0, 0.0, 0.0), regularizer="momentum-stress",
                    alpha=None, mesh=None, element_size=None, margin=None, initial=None, offset=None,
                    maxiter: int = 20, tol: float = 1e-3, linear_solver: str = "auto", regularizer_options=None,
                    normalize: bool = True, callback=None, strategy: str = "auto", repair: bool = True,
                    strain_tol=None, check_orientation: bool = True, refine=DEFAULT_REFINE, **ignored) -> VolumeResult:
    """Register ``moving`` to ``reference`` volumes: u minimising eq:objf = psi (eq:IR) + R on hexahedra.

    Parameters
    ----------
    reference_image, moving_image : (n_x, n_y, n_z) real arrays
        RF volumes (axial, lateral, elevational), same shape; ``reference(x) ~ moving(x + u(x))``.
    spacing : (dx, dy, dz) mm; origin : (3,) mm, the centre of voxel [0, 0, 0]
    regularizer, alpha, regularizer_options, maxiter, tol, linear_solver, callback, strain_tol, repair
        As in :func:`femreg.register` (alpha for 2 x 2 x 2 mm elements, scaled by element volume; "auto":
        chosen from the pair by :func:`femreg.autoalpha.choose_alpha`, 7 registrations, the choice in
        ``result.auto_alpha``).
    mesh : skfem.MeshHex1, optional
        An axis-aligned tensor hexahedral mesh (mm); default :func:`femreg.voxels.roi_mesh_3d` with
        ``element_size`` (default :data:`femreg.voxels.DEFAULT_ELEMENT_SIZE_3D`) and ``margin``.
    initial : None | "pyramid" | "zero" | VolumeResult | callable | (3 n_nodes,) array
        The start; None / "pyramid": :func:`coarse_to_fine`.  With an ``offset`` (a sequence increment) None is
        zero motion relative to S, and "pyramid" the pair's own coarse-to-fine field read at the nodes moved by S
        (eq:IR: I_1(x + S) ~ I_2(x + S + u)).
    offset : VolumeResult | callable | (3 n_nodes,) array, optional
        S of eq:IR (both volumes sampled at x + S(x)).
    refine : "default" | None | int | "auto" | femreg.refine.Refinement
        Adaptive refinement after the solve (:mod:`femreg.volume_refine`): x-, y-, z-slabs of the tensor mesh where
        the jumps of A[u] n across the faces stand out are halved and the pair solved again from the solution.
        "default": "auto" (:data:`femreg.volume_refine.VOLUME_REFINEMENT`) under the 2D rule
        (:func:`femreg.refine.default_refine`: ``strategy="auto"``, R_P_sigma, the default mesh, no offset, a
        numeric alpha), else off; None or 0: off.  The result's mesh, ``u`` and ``quality`` are the final mesh's,
        ``result.refinement`` what each pass split.
    roi, depth : "auto" | None | (x0, x1, y0, y1, z0, z1) mm; (d0, d1) mm, optional
        The region registered (:mod:`femreg.echo_volume`): "auto" (default) the box of usable echo, None the
        whole volume, a box or a depth range as given; the result keeps the full voxel grid and says what was
        left out (``excluded``, ``roi``).
    geometry : femreg.Swept, optional
        The volumes are a swept probe's (n_samples, n_lines, n_frames) with ``spacing`` = (dr mm, line pitch mm or
        deg, frame step deg): scan-converted inside the fan and registered here
        (:func:`femreg.swept.register_swept`; ``grid_spacing`` its option), returned as a
        :class:`femreg.volume_result.SweptResult`.

    Returns
    -------
    VolumeResult
        ``success`` False with a message when the result explains less of the volumes than its start (the start
        is returned), when the NCC after is below :data:`femreg.repair.MIN_NCC` or more than
        :data:`femreg.repair.MAX_POOR_FRACTION` of the elements are below it, when peak hopping remains, or when
        more than :data:`femreg.repair.MAX_HOPPED_FRACTION` of the elements match the envelope better one RF
        period off (:func:`hop_check`; the per-element gain is ``result.hop_gain``).
    """
    args = dict(locals())
    geometry = ignored.pop("geometry", None)
    if geometry is not None:            # a swept probe's volumes: scan-converted, then registered here (femreg.swept)
        from .probes import Swept, as_geometry
        from .swept import register_swept
        geo = as_geometry(geometry)
        if geo is not None and not isinstance(geo, Swept):
            raise InputError(f"a volume's geometry is femreg.Swept(...) (a swept probe) or None (a Cartesian "
                             f"grid), got {geo!r}")
        if geo is not None:
            kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image", "spacing", "origin",
                                                             "ignored")}
            kw["refine"] = _default_refine(refine, args, geometry=geo)     # not measured on swept volumes: off
            return register_swept(reference_image, moving_image, geometry=geo, spacing=spacing, origin=origin,
                                  register=register_volume, **kw, **ignored)
    routed = None if _DECIDING.get() else route_volume(register_volume, args)
    if routed is not None:              # inside the echo box or a given roi / depth (femreg.echo_volume)
        return routed
    unknown = {k for k in ignored if k not in _IGNORED_2D_OPTIONS}
    if unknown:
        raise InputError(f"unknown option(s) for volume registration: {', '.join(sorted(unknown))}")
    if isinstance(alpha, str):          # alpha="auto": chosen from the pair alone (femreg.autoalpha)
        return _register_auto(args)
    t_all = time.perf_counter()
    timings = {}
    opts = as_volume_refinement(_default_refine(refine, args))
    ref, mov, spacing, origin = _validate(reference_image, moving_image, spacing, origin, regularizer, strategy, maxiter, tol)
    if check_orientation:               # the central (axial, lateral) plane, as the 2D check reads a frame
        orientation.check(ref[:, :, ref.shape[2] // 2], spacing[:2], elevational=spacing[2])
    user_reg = fresh_regularizer(regularizer, alpha, effective_regularizer_options("auto", regularizer,
                                                                                   regularizer_options))

    def reg_factory():
        return copy.copy(user_reg)

    if normalize:
        ref, mov, _ = normalize_pair(ref, mov)

    if mesh is None:
        mesh = roi_mesh_3d(ref.shape, spacing, origin,
                           element_size=DEFAULT_ELEMENT_SIZE_3D if element_size is None else element_size,
                           margin=margin)
    elif tensor_axes_3d(mesh) is None:
        raise InputError("a volume mesh must be an axis-aligned tensor skfem.MeshHex1 (femreg.voxels.roi_mesh_3d)")
    S = None if offset is None else _voxel_offset(offset, VoxelGrid(mesh, ref.shape, spacing, origin))

    t = time.perf_counter()
    period = _rf_period_3d(ref, spacing)
    info = {}
    if initial is None or (isinstance(initial, str) and initial == "pyramid"):
        if S is None or initial is not None:     # an increment afresh: the pair's pyramid at x + S
            at = None if S is None else mesh.p.T + _offset_nodes(offset, mesh).reshape(-1, 3)
            u0, info = coarse_to_fine(ref, mov, spacing, origin, mesh, reg_factory, maxiter=maxiter, tol=tol,
                                      linear_solver=linear_solver, at=at)
            timings.update(info.pop("timings"))
            noise = unmatched_crop_volume(ref, mov, u0, mesh, spacing, origin, margin) if _cuts_at_depth(
                args) else None
            if _DECIDING.get():         # noise_at_depth_volume: the decision is all it asked for
                raise _CutDecided(noise)
            if noise is not None:       # no match at depth after the start: registered above it (femreg.echo)
                return registered_crop_volume(register_volume, noise, args)
        else:       # a sequence increment: start from zero motion relative to S
            u0 = np.zeros(3 * mesh.p.shape[1])
    elif isinstance(initial, str) and initial == "zero":
        u0 = np.zeros(3 * mesh.p.shape[1])
    elif isinstance(initial, str):
        raise InputError(f"initial must be 'pyramid', 'zero', a callable, a nodal vector or a VolumeResult, "
                         f"got {initial!r}")
    else:
        u0 = _start(initial, mesh)
    timings["initial"] = time.perf_counter() - t

    # the splines after the initial guess, whose envelope volumes then do not sit beside them; the moving
    # volume's samples are not needed once its coefficients exist
    t = time.perf_counter()
    shape = ref.shape
    I1, I2 = SplineVolume(ref, spacing, origin), SplineVolume(mov, spacing, origin, keep_data=False)
    del mov
    st = float(strain_tol) if strain_tol is not None else (
        GN_STRAIN_TOL_TIGHT if getattr(user_reg, "quadratic", False) else GN_STRAIN_TOL)
    kw = dict(maxiter=maxiter, tol=component_tol(tol, u0.reshape(-1, 3)[:, :2].ravel()),
              linear_solver=linear_solver, mask_outside=True, strain_tol=st if st > 0 else None)
    # the data term holds the reference values and gradients it needs: the reference volume and its spline go
    data = VoxelSSDTerm(VoxelGrid(mesh, shape, spacing, origin), I1, I2, offset=S)
    del I1, ref, S
    timings["prefilter"] = time.perf_counter() - t

    t = time.perf_counter()
    sol = solve_volume(None, I2, mesh, shape, spacing, origin, reg_factory, u0, callback=callback, data=data, **kw)
    del data
    timings["gauss_newton"] = time.perf_counter() - t

    t = time.perf_counter()
    notes, hops = [], np.zeros(mesh.p.shape[1], int)
    if repair:
        rkw = dict(kw, strain_tol=None if kw["strain_tol"] is None else min(kw["strain_tol"], GN_STRAIN_TOL_TIGHT))
        sol, hops, notes = _repair(sol, lambda u: solve_volume(None, I2, mesh, shape, spacing, origin,
                                                              reg_factory, u, data=sol.data, **rkw), mesh, period)
    unrefined = None
    if opts is not None and not hops.any() and int(maxiter) > 0:        # femreg.volume_refine
        unrefined = (sol, u0, hops, list(notes))
        t_ref = time.perf_counter()
        sol, u0, hops = _refine(sol, opts, u0, I2, shape, spacing, origin, reg_factory, kw)
        notes.append(sol.refinement.summary())
        timings["refine"] = time.perf_counter() - t_ref
    check = _check(sol, u0, hops, notes, period)
    if not check["success"] and unrefined is not None and sol is not unrefined[0]:
        # the refined result is judged on smaller elements (the poor and hopped fractions count elements): one
        # that fails its check gives way to the unrefined result and its own verdict (as in 2D)
        why = "; ".join(check["notes"][len(notes):]) or check["message"]
        sol, u0, hops, notes = unrefined
        check = _check(sol, u0, hops, notes + [f"refinement dropped (the refined result failed its check: {why})"],
                       period)
    mesh = sol.mesh
    timings["hop_check_cpu"] = check["hop_check_cpu"]
    timings["check"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    res = VolumeResult(mesh, check["u"], shape=shape, spacing=spacing, origin=origin, regularizer=sol.reg.name,
                       alpha=user_reg.alpha, success=check["success"], status=sol.gn.status, message=check["message"],
                       nit=sol.gn.nit, energy_history=sol.gn.energy_history, ncc_before=check["ncc_before"],
                       ncc_after=check["ncc_after"], timings=timings, quality=check["quality"], strategy="auto",
                       alpha_effective=sol.reg.alpha, solver_result=sol.gn)
    if getattr(sol, "refinement", None) is not None:
        res.refinement = sol.refinement
    res.hop_gain = check["hop_gain"]    # per element (mesh.t order), femreg.repair.hop_gain's measure
    res.initial_info = info
    return res


def _cuts_at_depth(args: dict) -> bool:
    """Whether :func:`register_volume` (its arguments ``args``) looks for noise at depth after its start (the 2D
    rule, :func:`femreg.registration.register`): only where it detects the echo itself (``roi="auto"``, nothing
    given that fixes the region)."""
    extra = args.get("ignored") or {}
    return (isinstance(extra.get("roi", "auto"), str) and extra.get("depth") is None and args["mesh"] is None
            and args["initial"] is None and args["offset"] is None)


#: Set while :func:`noise_at_depth_volume` runs :func:`register_volume` for its cut alone (:class:`_CutDecided`).
_DECIDING = contextvars.ContextVar("femreg_volume_deciding", default=False)


class _CutDecided(Exception):
    """Ends :func:`register_volume` under :func:`noise_at_depth_volume` once its start's cut is decided."""

    def __init__(self, crop):
        super().__init__("the cut at depth is decided")
        self.crop = crop


def noise_at_depth_volume(reference, moving, *, spacing, origin=(0.0, 0.0, 0.0), **register_kwargs):
    """The crop :func:`register_volume` would cut the pair to after its start for noise at depth
    (:func:`femreg.echo_volume.unmatched_crop_volume`), or None; the volumes' :func:`femreg.registration.noise_at_depth`
    for :func:`track_volume`, which chooses one box for the loop from its first two volumes.  :func:`register_volume`
    itself runs up to that decision (validation, normalisation, the default mesh, :func:`coarse_to_fine`), with
    the options of ``register_kwargs`` that make its start (:data:`_START_OPTIONS`; ``alpha="auto"`` starts from
    the default) and none of its hand-offs (echo box, ``alpha="auto"``: the caller has made those choices)."""
    kw = {k: v for k, v in register_kwargs.items() if k in _START_OPTIONS}
    if isinstance(kw.get("alpha"), str):
        kw["alpha"] = None
    token = _DECIDING.set(True)
    try:
        register_volume(reference, moving, spacing=spacing, origin=origin, check_orientation=False, **kw)
    except _CutDecided as decided:
        return decided.crop
    finally:
        _DECIDING.reset(token)
    return None


def _register_auto(args: dict) -> VolumeResult:
    """``register_volume(..., alpha="auto")`` (``args``: its arguments, the region already routed):
    :func:`femreg.autoalpha.register_auto` with this module's registration and image term; the pair is
    validated and its orientation checked once, before the candidates."""
    if args["alpha"] != "auto":
        raise InputError(f"alpha must be a number or 'auto', got {args['alpha']!r}")
    ref, mov = args["reference_image"], args["moving_image"]
    vol, _, spacing, _ = _validate(ref, mov, args["spacing"], args["origin"], args["regularizer"],
                                   args["strategy"], args["maxiter"], args["tol"])
    if args["check_orientation"]:
        orientation.check(vol[:, :, vol.shape[2] // 2], spacing[:2], elevational=spacing[2])
    del vol
    kw = {k: v for k, v in args.items() if k not in ("reference_image", "moving_image", "ignored")}
    kw.update(args["ignored"], roi=None, depth=None, check_orientation=False)
    kw["refine"] = _default_refine(args["refine"], args)       # the default is off for alpha="auto" (as in 2D)
    return register_auto(ref, mov, register=register_volume, image_term=voxel_image_term, **kw)


#: Options of :func:`register_volume` that make its start (:func:`noise_at_depth_volume`).
_START_OPTIONS = ("regularizer", "alpha", "element_size", "margin", "maxiter", "tol", "linear_solver",
                  "regularizer_options", "normalize")

#: Options of the 2D :func:`femreg.register` that have no meaning on volumes and are accepted and ignored.
_IGNORED_2D_OPTIONS = ("roi", "depth", "geometry", "blockmatch_options", "coarse_to_fine",
                       "allow_mesh_outside")


@dataclass
class VolumeTrack:
    """Displacements from frame 0 of a volume sequence: ``results[k]`` the increment k -> k + 1 (a
    :class:`VolumeResult` on the frame-0 mesh, eq:IR with S the accumulated field), ``accumulated[k]`` frame 0 ->
    k + 1 (u = S + du on the same mesh); ``success`` all increments succeeded.  ``flags[k]``: '' or why frame
    k + 1 is flagged (its registration failed its own check, or its NCC after is below ``min_ncc``);
    ``computed[k]``: False where the frame was loaded from a checkpoint; ``retried``: the frames whose increment,
    started from the previous one, was flagged and registered again from a fresh start (as
    :attr:`femreg.sequence.SequenceResult.retried`).  A swept probe's sequence holds
    :class:`~femreg.volume_result.SweptResult` entries and ``swept`` its :class:`femreg.swept.SweptConversion`."""

    results: list
    accumulated: list
    flags: list = field(default_factory=list)
    computed: list = field(default_factory=list)
    swept: object = None
    repeated: list = field(default_factory=list)
    retried: list = field(default_factory=list)

    @property
    def success(self) -> bool:
        return all(r.success for r in self.results)

    def __len__(self):
        return len(self.accumulated)

    def __getitem__(self, k):
        """Frame 0 -> k + 1, as a 2D :func:`femreg.track` result is indexed."""
        return self.accumulated[k]


@single_blas_thread
def track_volume(frames, *, spacing, origin=(0.0, 0.0, 0.0), mode: str = "accumulate", progress=False,
                 checkpoint_dir=None, resume: bool = False, min_ncc=None, on_frame=None, geometry=None,
                 grid_spacing=None, **register_kwargs) -> VolumeTrack:
    """Track a volume sequence (n_frames, n_x, n_y, n_z): ``mode="accumulate"`` registers frame k to k + 1 on
    the frame-0 grid with S = the accumulated field (eq:IR, both frames sampled at x + S; the previous increment
    starts the next; one flagged from it is registered again from a fresh start, the pair's coarse-to-fine field
    read at x + S (``initial="pyramid"`` of :func:`register_volume`), and the fresh result kept unless it is
    flagged too, then the one with the higher NCC after, as :func:`femreg.track` does with frames; an increment
    after a flagged or retried one starts afresh), ``"direct"`` frame 0 to every later frame independently.
    ``roi`` / ``depth`` (as in :func:`register_volume`; "auto" from frames 0 and 1): every frame is registered
    inside the same box.
    ``alpha="auto"``: chosen on frames 0 -> 1 (:func:`femreg.autoalpha.choose_alpha`) and used for every
    registration, as :func:`femreg.track` does; every result's ``auto_alpha`` records the choice.

    ``geometry=femreg.Swept(...)``: the volumes are a swept probe's (n_samples, n_lines, n_frames), ``spacing``
    and ``origin`` as for :func:`register_volume`; every volume is scan-converted once onto the Cartesian grid of
    frame 0 (:func:`femreg.swept.scan_convert_sequence`, ``grid_spacing`` its option) and that sequence tracked
    here; the results are :class:`~femreg.volume_result.SweptResult` (physical Cartesian mm; ``on_grid`` at the
    samples).

    ``checkpoint_dir``, ``resume``, ``progress``, ``min_ncc``, ``on_frame(k, result, flag)``: as in
    :func:`femreg.track` (``frame_KKK.npz`` = frame 0 -> K with its ``increment`` and ``flag``, ``track.json`` the
    parameters; :func:`femreg.load_track` reads the folder)."""
    arr = [np.asarray(f) for f in frames]
    if len(arr) < 2:
        raise InputError(f"a sequence needs at least 2 volumes, got {len(arr)}")
    if any(a.ndim != 3 for a in arr):
        raise InputError("every frame of a volume sequence must be 3D (axial, lateral, elevational)")
    if mode not in ("accumulate", "direct"):
        raise InputError(f"mode must be 'accumulate' or 'direct', got {mode!r}")
    if min_ncc is not None and not np.isfinite(float(min_ncc)):
        raise InputError(f"min_ncc must be a finite number or None, got {min_ncc!r}")
    from .image import refuse_repeated_start, repeat_note, repeated_frames
    # a volume written twice: nothing moved (as femreg.track's frames: kept, not registered)
    repeats = repeated_frames(arr)
    refuse_repeated_start(repeats, len(arr))
    repeats = set(repeats)
    swept = None
    if geometry is not None:            # a swept probe's volumes: one Cartesian grid for all (femreg.swept)
        from .probes import Swept, as_geometry
        from .swept import scan_convert_sequence
        geo = as_geometry(geometry)
        if not isinstance(geo, Swept):
            raise InputError(f"a volume's geometry is femreg.Swept(...) (a swept probe) or None (a Cartesian "
                             f"grid), got {geo!r}")
        for bad in ("mesh", "offset"):
            if register_kwargs.get(bad) is not None:
                raise InputError(f"{bad}= is not supported with a swept geometry (the mesh is built on the "
                                 "scan-converted grid)")
        arr, swept = scan_convert_sequence(arr, geo, spacing, origin, grid_spacing=grid_spacing)
        _, spacing, origin = swept.cartesian
    elif grid_spacing is not None:
        raise InputError("grid_spacing is an option of a swept probe's volumes (geometry=femreg.Swept(...))")
    if register_kwargs.pop("check_orientation", True):
        sp3 = validate_spacing_3d(spacing, origin)[0]
        orientation.check(validate_volume(arr[0], "frame 0")[:, :, arr[0].shape[2] // 2], sp3[:2],
                          elevational=sp3[2])
    register_kwargs["check_orientation"] = False    # checked once, above
    # refinement is opt-in for a sequence, as in 2D (femreg.track): its meshes are the frame-0 one
    register_kwargs["refine"] = _default_refine(register_kwargs.get("refine", DEFAULT_REFINE), {"mesh": True})
    roi, depth = register_kwargs.pop("roi", "auto"), register_kwargs.pop("depth", None)
    crop = crop_for_volume(arr[0], arr[1], spacing, origin, roi=roi, depth=depth, mesh=register_kwargs.get("mesh"),
                           margin=register_kwargs.get("margin"))
    shape = tuple(int(v) for v in arr[0].shape)
    if crop is None and _cuts_at_depth({"ignored": {"roi": roi, "depth": depth}, "mesh": register_kwargs.get("mesh"),
                                        "initial": register_kwargs.get("initial"),
                                        "offset": register_kwargs.get("offset")}):
        # noise a TGC lifts at depth: the cut register_volume makes, decided once from frames 0 and 1
        crop = noise_at_depth_volume(arr[0], arr[1], spacing=spacing, origin=origin, **register_kwargs)
    if crop is not None:                # every frame inside the box of frames 0 and 1 (femreg.echo_volume)
        arr, origin = crop.frames(*arr), crop.origin
    register_kwargs.update(roi=None, depth=None)
    mesh = register_kwargs.pop("mesh", None)
    auto = None
    if isinstance(register_kwargs.get("alpha"), str):   # "auto": chosen on the first pair, reused (as femreg.track)
        if register_kwargs["alpha"] != "auto":
            raise InputError(f"alpha must be a number or 'auto', got {register_kwargs['alpha']!r}")
        auto = choose_alpha(arr[0], arr[1], register=register_volume, image_term=voxel_image_term, spacing=spacing,
                            origin=origin, mesh=mesh, progress=progress, **register_kwargs)
        auto.result = None
        register_kwargs["alpha"] = auto.alpha
    ckpt = None
    if checkpoint_dir is not None or resume:
        from ._atomic import open_run_folder
        params = {"n_frames": len(arr), "shape": list(shape), "spacing": [float(v) for v in np.ravel(spacing)],
                  "origin": [float(v) for v in np.ravel(origin)], "mode": mode, "volume": True,
                  "register_kwargs": json.loads(json.dumps({k: v for k, v in register_kwargs.items()
                                                            if k != "check_orientation"}, sort_keys=True,
                                                           default=repr)),
                  "roi": None if crop is None else [float(v) for v in crop.region.roi_mm],
                  "user_mesh": mesh is not None}
        if swept is not None:
            params["swept"] = swept.params()
        ckpt = open_run_folder(checkpoint_dir, params, resume=resume, record="track.json",
                               started=("frame_*.npz",), kind="a tracking run", argument="checkpoint_dir")

    def finish(r):
        """A result on the crop as the sequence's result: the full grid, the alpha choice, a swept probe's."""
        if crop is not None:
            crop.widen(r)
        if auto is not None:
            r.auto_alpha = auto
        return r if swept is None else swept.result(r)

    out = VolumeTrack(results=[], accumulated=[], swept=swept)
    S = None
    prev = None
    tainted = None                      # (frame, why) of the first flagged increment, accumulate mode
    prev_own_flag = ""                  # the last increment's own flag: a fresh start follows it, not a taint
    from ._atomic import load_frame_record, progress_bar, save_frame
    bar = progress_bar(progress, len(arr) - 1, f"track volumes ({mode})", "volume", on_frame)
    try:
        for k in range(1, len(arr)):
            path = None if ckpt is None else ckpt / f"frame_{k:03d}.npz"
            retried = ""
            if resume and path is not None and path.exists():
                from .volume_result import load_volume_result
                a = load_volume_result(path)
                inc, flag, retried = load_frame_record(path)
                r = a if mode == "direct" else copy.copy(a)
                if r is not a:
                    r.u, r._nodal_strain, r._grids = inc, None, {}
                computed = False
            elif k in repeats:
                # frame 0 -> k is frame 0 -> k - 1; the increment is zero
                note = repeat_note(k)
                a = copy.copy(out.accumulated[-1])
                a.message = f"{a.message}; {note}" if a.message else note
                a.repeats = k - 1
                r = a if mode == "direct" else copy.copy(out.results[-1])
                if r is not a:
                    r.u, r._nodal_strain, r._grids = np.zeros_like(np.asarray(r.u, float)), None, {}
                flag, computed = out.flags[-1], True
                if path is not None:
                    save_frame(path, a, np.asarray(r.u, float), flag, k, mode)
            else:
                if mode == "direct":
                    r = finish(register_volume(arr[0], arr[k], spacing=spacing, origin=origin, mesh=mesh,
                                               **register_kwargs))
                    a = r
                else:
                    def increment(start):
                        """(frame 0 -> k, the increment k - 1 -> k) registered from ``start``."""
                        kw = dict(register_kwargs)
                        if S is not None:
                            kw["initial"] = start
                        r = register_volume(arr[k - 1], arr[k], spacing=spacing, origin=origin, offset=S,
                                            mesh=mesh if S is None else out.accumulated[-1].mesh, **kw)
                        a = copy.copy(r)
                        a.u = r.u if S is None else S + r.u
                        a._nodal_strain = None
                        a._grids = {}
                        r, a = finish(r), finish(a)
                        return a, r

                    # a user's start is every increment's; else the previous increment, and when that is flagged
                    # the pair's own pyramid read at x + S (zero motion relative to S cannot follow a jump)
                    fresh = S is None or bool(prev_own_flag) or "initial" in register_kwargs
                    a, r, retried = retry_flagged(increment, prev.u if prev is not None else "zero",
                                                  register_kwargs.get("initial", "pyramid"), fresh, min_ncc, k)
                    if retried:
                        r.message = a.message   # the increment's result says so too
                    if tainted is not None:     # the accumulated field adds a flagged increment
                        mark_tainted(a, *tainted)
                flag = frame_flag(a, min_ncc)
                computed = True
                if path is not None:
                    save_frame(path, a, r.u, flag, k, mode, retried)
            if retried:
                out.retried.append(k)
                a.retried = retried     # for on_frame (the file keeps it as "retried")
            own = own_flag(a, flag, min_ncc)
            if own and mode == "accumulate" and tainted is None and k not in repeats:
                tainted = (k, own)
            if k not in repeats:
                # a retried increment's start from the previous one failed: the next starts fresh as well
                prev_own_flag = own or retried
            out.results.append(r)
            out.accumulated.append(a)
            out.flags.append(flag)
            out.computed.append(computed)
            if k in repeats:
                out.repeated.append(k)      # prev stays the last registered increment: the next one's start
            elif mode == "accumulate":
                S, prev = np.asarray(a.u, float), r
            if on_frame is not None:
                on_frame(k, a, flag)
            if bar is not None:
                bar.set_postfix_str(f"ncc {r.ncc_after:.2f}" + (" FLAGGED" if flag else ""))
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return out


def volumes_to(register_2d):
    """Decorator of :func:`femreg.register`: a pair of 3D arrays (volumes) is registered by
    :func:`register_volume` with the same keywords, anything else by ``register_2d`` unchanged."""
    @functools.wraps(register_2d)
    def register(reference_image, moving_image, **kwargs):
        require_spacing(kwargs.get("spacing"))
        if (np.ndim(reference_image) == 3 and np.shape(reference_image)[0] >= 2 and np.size(kwargs["spacing"]) == 2
                and kwargs.get("geometry") is None):
            raise InputError(f"reference_image is 3D, shape {np.shape(reference_image)}, with a spacing of two "
                             "values: a stack of frames? register takes one frame each, register(frames[0], "
                             "frames[1], ...), and femreg.track(frames, ...) follows a sequence; a volume takes "
                             "spacing (dx, dy, dz)")
        if np.ndim(reference_image) == 3:
            if kwargs.pop("data_mask", None) is not None:
                raise InputError("data_mask is for frames (n_axial, n_lateral); volumes take roi / depth")
            return register_volume(reference_image, moving_image, **kwargs)
        return register_2d(reference_image, moving_image, **kwargs)
    return register
