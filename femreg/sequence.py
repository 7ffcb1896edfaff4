"""Frame sequences: accumulated displacement by eq:IR, and direct frame-0 -> frame-k registration.

Accumulation (paper eq:IR): the increment u_k registers I_k(x + S_k) to I_{k+1}(x + S_k + u_k), where
S_k = u_0 + ... + u_{k-1} is the accumulated field in frame-0 coordinates; all increments share the nodes of ONE
mesh (over frame 0), so S_{k+1} = S_k + u_k is a sum of nodal vectors.  Frame k's result is S_k: the displacement
from frame 0 to frame k at frame-0 positions, the quantity every metric of the paper compares with the truth.

Two ways to evaluate eq:IR (``grid``):

* ``"current"`` (default): the change of variables y = x + S_k(x) turns eq:IR into a registration of I_k and
  I_{k+1} on frame k's own pixel grid, over the frame-0 mesh moved by S_k (same nodes, same element
  connectivity).  I_k is sampled exactly at its pixels, never interpolated.
* ``"reference"``: the literal form, both frames interpolated at x + S_k on the frame-0 pixel grid.  Sampling
  noisy frames between pixels changes the interpolated noise variance with the sub-pixel position, which biases
  the tiny lateral increments; the bias accumulates.  Measured on the 3D HI sequence (12 dB, R_P_sigma,
  frames 1 -> 20): total strain error 40.4 % (u_y 85 %) with "reference", 14.2 % (u_y 6.8 %) with "current",
  at the same cost.

Convex / sector frames (``geometry=femreg.Convex(...)`` or ``femreg.Sector(...)``, frames (n_samples, n_rays),
``spacing=dr``, ``origin=(r0, 0)``): every pair is registered by :func:`femreg.geometry.register_beam`; the mesh is
the physical mesh of the first pair's registration, and each increment is registered on frame k's own samples over
that mesh moved by S_k (the ``"current"`` form above, in physical coordinates), so S_{k+1} = S_k + u_k is still a
nodal sum.  The results are :class:`femreg.geometry.BeamResult` (measured: docs/geometry.md, "Sequences").

Checkpoints: with ``checkpoint_dir`` each frame's result is written (atomically) as soon as it is done; with
``resume=True`` finished frames are loaded instead of recomputed.  A frame that fails (error, or a registration
flagged by the quality check) is recorded and, in accumulation, the run stops there without losing the earlier
frames.
"""
from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path

import numpy as np
from skfem import MeshQuad1

from ._atomic import atomic_write_text, load_frame_record, open_run_folder, progress_bar, save_frame
from .echo import as_data_mask, crop_for
from . import orientation
from .errors import InputError, pass_as
from .initial import Previous
from .image import (refuse_repeated_start, repeat_note, repeated_frames, require_spacing, validate_image,
                    validate_spacing)
from .mesh import as_quad_mesh, check_element_size, roi_mesh
from .pyramid import default_settings, element_rule, speckle_statistics
from .geometry import BeamResult, beam_image_term, beam_spacing, default_beam_alpha_factor, sample_space
from .probes import Convex, as_geometry
from .registration import RegistrationResult, noise_at_depth, register, sharing_start
from .result import load_result
from .repair import frame_flag, mark_tainted, own_flag, retry_flagged
from .solver import single_blas_thread

__all__ = ["track", "SequenceResult", "load_track", "TRACK_HOURGLASS"]

#: Flag a pair as low quality when the NCC after registration is below this value.
DEFAULT_MIN_NCC = 0.5
#: Hourglass-control weight (relative to alpha) of the momentum regularisers for the increments of an accumulated
#: track with ``strategy="auto"`` (a single registration uses
#: :data:`femreg.registration.DEFAULT_HOURGLASS` = 100).  The edge-jump TV term is re-weighted by ``1 / |jump|``
#: (lagged diffusivity), so on the small increments of a sequence it grows against the quadratic hourglass term,
#: and the checkerboard left in each increment adds up over the frames.  Measured, in vivo frames 1 -> 6
#: (R_P_sigma, femreg.quality.hourglass of u_y / NCC of frame 6 warped onto frame 1), weight 100 / 1000 / 10000:
#: seq299 21.0 / 8.7 / 2.2 um, NCC 0.781 / 0.775 / 0.771 (e_yy column stripes gone at 1000); seq304 4.1 / 2.2 /
#: 0.8 um, NCC 0.880 / 0.879 / 0.876; 3D HI sequence frames 1 -> 20 total strain error 14.2 % at 100 and 1000.
TRACK_HOURGLASS = 1000.0


class SequenceResult(list):
    """A list of :class:`~femreg.registration.RegistrationResult`, one per frame 1..N-1 (entry k-1 = frame 0 ->
    frame k), with per-frame bookkeeping.

    Attributes
    ----------
    mode : "accumulate" | "direct"
    increments : list of (2 n_nodes,) arrays
        The increments u_k of eq:IR (accumulate mode; equal to the results themselves in direct mode).
    flags : list of str
        '' for a good frame, otherwise why it is flagged (NCC after registration below ``min_ncc``).
    computed : list of bool
        True where the frame was computed in this call, False where it was loaded from a checkpoint.
    repeated : list of int
        Frames k whose samples equal frame k - 1's (a frame written twice): not registered, their entry is frame
        k - 1's field (accumulate: a zero increment), the message saying so.
    retried : list of int
        Frames k whose increment, started from the previous increment (``init="previous"``), was flagged and was
        registered again from a fresh start (accumulate mode); the message of each says why and which was kept.
    """

    def __init__(self, results=(), *, mode="accumulate"):
        super().__init__(results)
        self.mode = mode
        self.increments = []
        self.flags = []
        self.computed = []
        self.repeated = []
        self.retried = []


def _validate_frames(frames):
    if isinstance(frames, np.ndarray):
        if frames.ndim != 3:
            raise InputError(f"frames must be a 3D array (n_frames, n_axial, n_lateral), got ndim={frames.ndim}")
        seq = [frames[k] for k in range(frames.shape[0])]
    else:
        seq = list(frames)
    if len(seq) < 2:
        raise InputError(f"need at least 2 frames to track, got {len(seq)}")
    seq = [validate_image(f, f"frame {k}") for k, f in enumerate(seq)]
    odd = [k for k, f in enumerate(seq) if f.shape != seq[0].shape]
    if odd:
        raise InputError(f"all frames must have the same shape: frame 0 {seq[0].shape}, frame {odd[0]} "
                         f"{seq[odd[0]].shape}" + (f" ({len(odd)} frames differ from frame 0)" if len(odd) > 1 else ""))
    return seq


def _params_record(n_frames, shape, spacing, origin, mode, regularizer, alpha, mesh, init):
    reg_name = regularizer if isinstance(regularizer, str) else getattr(regularizer, "name", type(regularizer).__name__)
    # mesh None: made by the first pair's registration (convex / sector frames), from the frames and settings
    n = None if mesh is None else mesh.p.shape[1]
    return {"n_frames": int(n_frames), "shape": [int(s) for s in shape],
            "spacing": [float(s) for s in np.atleast_1d(spacing)], "origin": [float(s) for s in origin],
            "mode": mode, "regularizer": str(reg_name), "alpha": None if alpha is None else float(alpha),
            "n_nodes": None if n is None else int(n),
            "mesh_checksum": None if n is None else float(np.round(np.sum(mesh.p * np.arange(1, n + 1)), 6)),
            "init": str(init)}


def _record_beam_region(pfile, res) -> None:
    """``registered_region`` of a convex / sector track's record from its first pair's sample-space crop
    (``res.sample_space.roi``, (range, arc) mm): the rows and rays of the frames registered, its shape and its
    first range (the record written at the start, before the first pair, holds the whole frames)."""
    inner = getattr(res, "sample_space", None)
    roi = None if inner is None else getattr(inner, "roi", None)
    if roi is None:
        return
    (dr, ds), (r0, s0) = inner.spacing, inner.origin
    rows = [int(round((roi[0] - r0) / dr + 0.5)), int(round((roi[1] - r0) / dr + 0.5))]
    cols = [int(round((roi[2] - s0) / ds + 0.5)), int(round((roi[3] - s0) / ds + 0.5))]
    rec = json.loads(pfile.read_text())
    rec["registered_region"] = {"rows": rows, "cols": cols, "shape": [rows[1] - rows[0], cols[1] - cols[0]],
                                "origin": [float(r0 + rows[0] * dr), 0.0]}
    atomic_write_text(pfile, json.dumps(rec, indent=1))


def _region_record(shape, origin, crop) -> dict:
    """The entries of ``track.json`` that say what ``shape`` and ``origin`` are: the frames' (and the results')
    ``frame_shape`` / ``frame_origin``, and the ``registered_region`` (half-open pixel ``rows`` and ``cols`` of
    the frames, its ``shape`` and ``origin`` in mm) that ``shape`` and ``origin`` describe, kept under those
    names for the readers of earlier files."""
    if crop is None:
        full, full_origin, rows, cols = shape, origin, (0, shape[0]), (0, shape[1])
    else:
        full, full_origin = crop.region.shape, crop.region.origin
        rows, cols = ((s.start, s.stop) for s in crop.slices)
    return {"frame_shape": [int(v) for v in full], "frame_origin": [float(v) for v in full_origin],
            "registered_region": {"rows": [int(v) for v in rows], "cols": [int(v) for v in cols],
                                  "shape": [int(v) for v in shape], "origin": [float(v) for v in origin]},
            "shape_note": "shape and origin: the registered region (registered_region, rows x lines of the "
                          "frames); the frames and the results in frame_KKK.npz: frame_shape, frame_origin"}


@single_blas_thread
@sharing_start()    # the first pair's registration takes the start its noise-at-depth decision made on it
def track(frames, *, spacing=None, origin=(0.0, 0.0), regularizer="momentum-stress", alpha=None,
          mode: str = "accumulate", grid: str = "current",
          init: str = "previous", mesh=None, element_size=None, margin=None, checkpoint_dir=None,
          resume: bool = False, progress: bool = False, min_ncc: float = DEFAULT_MIN_NCC,
          on_frame=None, roi="auto", depth=None, check_orientation: bool = True, data_mask=None,
          **register_kwargs) -> SequenceResult:
    """Displacement from frame 0 to every later frame of a sequence.

    Parameters
    ----------
    frames : (n_frames, n_axial, n_lateral) array or sequence of 2D arrays
        RF frames, all of one shape.  A 4D array or a sequence of 3D arrays is a volume sequence, tracked by
        :func:`femreg.volume.track_volume` (a :class:`femreg.volume.VolumeTrack` is returned); with
        ``geometry=femreg.Swept(...)`` a swept probe's volumes (n_samples, n_lines, n_frames), all scan-converted
        onto one Cartesian grid and tracked there (results :class:`femreg.SweptResult`; ``grid_spacing`` as in
        :func:`femreg.register`).
    spacing, origin : (2,) mm
        Pixel spacing (axial, lateral) and the centre of pixel [0, 0]; ``spacing`` is required (None: an
        :class:`~femreg.errors.InputError` saying what it is).
    regularizer, alpha
        As in :func:`femreg.register` (name or Regularizer instance; None alpha = documented default; "auto" =
        chosen on the first pair by :func:`femreg.autoalpha.choose_alpha`, with the fan's mask of ``data_mask``,
        and reused for every pair).
    mode : {"accumulate", "direct"}
        "accumulate": eq:IR, increments between consecutive frames carried in frame-0 coordinates.
        "direct": frame 0 -> frame k registered independently (the paper's dual-frame comparisons).
    grid : {"current", "reference"}
        How accumulation evaluates eq:IR: on each frame's own pixel grid with the mesh moved by S_k (default),
        or on the frame-0 grid with both frames interpolated at x + S_k (literal; biased laterally on noisy data,
        see the module docstring).
    init : {"previous", "blockmatch"}
        Initial guess of each increment (accumulate mode): the previous increment (default: consecutive
        increments of a compression sequence are alike), or NCC block matching every time (paper).  The first
        increment, and any increment after a flagged or retried one, starts afresh (the strategy's own initial
        guess: the pyramid of ``strategy="auto"``, block matching with ``"paper"``); direct mode always starts
        afresh.  An increment started from the previous one that is flagged (e.g. peak hopping where the
        compression per frame varies) is registered again from a fresh start, and the fresh result is kept unless
        it is flagged too (then the one with the higher NCC after registration); ``SequenceResult.retried`` lists
        those frames.  An increment whose frames match at least as well with no motion as with the previous
        increment (a nearly still frame after a moving one) starts afresh at once, its message saying "started
        afresh" (:class:`femreg.initial.Previous`): from the previous increment the solve stayed an RF period off.
    mesh, element_size, margin
        One mesh over frame 0 for every frame (default ROI mesh of :func:`femreg.mesh.roi_mesh`, elements sized
        from frame 0's speckle as :func:`femreg.register` does with ``strategy="auto"``).
    checkpoint_dir : path, optional
        Write ``frame_KKK.npz`` (frame 0 -> K result, plus the increment) as each frame finishes, and
        ``track.json`` with the parameters.
    resume : bool
        Load finished frames from ``checkpoint_dir`` instead of recomputing them; the parameters must match.
    progress : bool
        Show a tqdm progress bar on stderr.
    min_ncc : float
        Frames whose registration NCC (after) is below this, or whose registration failed its own check
        (``success=False``), are flagged (the run continues).
    on_frame : callable(k, result, flag), optional
        Called after each frame (computed or loaded).  One with a true ``reports_progress`` attribute prints its
        own line per frame: off a terminal the progress lines are then left out (one line per frame).
    roi, depth
        As in :func:`femreg.register`: the region tracked, from frames 0 and 1 ("auto", default: the echo
        rectangle of :func:`femreg.echo.find_echo`; where it cuts nothing, the rows at depth where frames 0 and 1
        do not match after the default start's block matching, noise a time-gain compensation lifts to the echo's
        level, as :func:`femreg.register` cuts a pair: :func:`femreg.registration.noise_at_depth`), the whole
        frames (None), or a given rectangle / depth range (mm); every frame is registered inside it and the
        results say what was excluded.  Volumes: the box of
        :mod:`femreg.echo_volume`, a given (x0, x1, y0, y1, z0, z1) or depth range.
    check_orientation : bool
        Refuse frames that look transposed or a spacing that looks swapped, from frame 0's RF carrier, before any
        registration (:mod:`femreg.orientation`; as :func:`femreg.register`).  False skips the check.
    data_mask : None | (n_axial, n_lateral) bool array
        As in :func:`femreg.register`, for every frame: where the frames hold data (True; e.g. a scan-converted
        fan); None: found from frames 0 and 1 with ``roi="auto"``.  Not for convex / sector geometries or volumes.
    geometry : femreg.Convex | femreg.Sector | femreg.Swept, optional (keyword)
        Convex / sector frames (n_samples, n_rays) along rays: ``spacing`` is the range step dr mm (or (dr mm,
        dtheta deg)), ``origin`` (r0 mm, 0); the first pair's registration makes the physical mesh (``roi``,
        ``depth``, ``element_size``, ``margin`` apply to it); entries are :class:`femreg.geometry.BeamResult`;
        ``alpha="auto"`` is chosen on the first pair on a grid centred on the beam's default alpha (times
        :func:`femreg.geometry.beam_alpha_factor`); ``grid="reference"`` is not supported.  Swept: volumes (above).
    **register_kwargs
        Passed to :func:`femreg.register` (maxiter, tol, linear_solver, blockmatch_options, ...).

    Returns
    -------
    SequenceResult
        Entry k-1 is frame 0 -> frame k, a RegistrationResult (BeamResult with a convex / sector geometry) on the
        common mesh in frame-0 coordinates.
    """
    require_spacing(spacing)
    if len(frames) and np.ndim(frames[0]) == 3:     # a sequence of RF volumes: femreg.volume
        if data_mask is not None:
            raise InputError("data_mask is for frames (n_axial, n_lateral); volumes take roi / depth")
        from .volume import track_volume
        return track_volume(frames, spacing=spacing, origin=origin, mode=mode, regularizer=regularizer, alpha=alpha,
                            mesh=mesh, element_size=element_size, margin=margin,
                            check_orientation=check_orientation, roi=roi, depth=depth, checkpoint_dir=checkpoint_dir,
                            resume=resume, progress=progress, min_ncc=min_ncc, on_frame=on_frame, **register_kwargs)
    if mode not in ("accumulate", "direct"):
        raise InputError(f"mode must be 'accumulate' or 'direct', got {mode!r}")
    if grid not in ("current", "reference"):
        raise InputError(f"grid must be 'current' or 'reference', got {grid!r}")
    if init not in ("blockmatch", "previous"):
        raise InputError(f"init must be 'blockmatch' or 'previous', got {init!r}")
    seq = _validate_frames(frames)
    # a frame written twice: nothing moved, registering it would run to the iteration limit on u = 0
    repeats = repeated_frames(seq)
    refuse_repeated_start(repeats, len(seq))
    beam = as_geometry(register_kwargs.pop("geometry", None))
    if isinstance(beam, Convex):        # convex / sector frames: femreg.geometry, results in physical x, y
        if data_mask is not None:
            raise InputError("data_mask is on a Cartesian pixel grid: not with a convex / sector geometry")
        return _track_beam(seq, beam, spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                           mode=mode, grid=grid, init=init, mesh=mesh, element_size=element_size, margin=margin,
                           checkpoint_dir=checkpoint_dir, resume=resume, progress=progress, min_ncc=min_ncc,
                           on_frame=on_frame, roi=roi, depth=depth, check_orientation=check_orientation,
                           register_kwargs=register_kwargs)
    if beam is not None:
        raise InputError("a femreg.Swept geometry is a swept probe's: track its volumes (n_samples, n_lines, "
                         "n_frames), not frames")
    one_value = np.ndim(spacing) == 0
    spacing, origin = validate_spacing(spacing, origin)
    if check_orientation:
        orientation.check(seq[0], spacing, one_value=one_value)
    register_kwargs["check_orientation"] = False    # checked once, above
    crop = crop_for(seq[0], seq[1], spacing, origin, roi=roi, depth=depth, mesh=mesh, margin=margin, fan=True,
                    data_mask=data_mask)
    if crop is None:               # nothing cut by level: noise lifted by a TGC at depth, as register cuts it
        crop = noise_at_depth(seq[0], seq[1], spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                              mesh=mesh, element_size=element_size, margin=margin, roi=roi, depth=depth,
                              data_mask=data_mask, **register_kwargs)
    if crop is not None:           # every frame inside the echo rectangle; results widened to the full grid
        seq, origin = crop.frames(*seq), np.asarray(crop.origin)
        # a fan: its fill weighted 0 in every pair's eq:IR (femreg.echo.DataMask)
        register_kwargs["data_mask"] = crop.mask
    else:                          # a user's mask on the frames not cut to it (roi=None, a user mesh)
        register_kwargs["data_mask"] = as_data_mask(data_mask, seq[0].shape, spacing)
    uncut = None if crop is not None or register_kwargs["data_mask"] is None else register_kwargs["data_mask"].inside
    # a resume with another mask is refused (its digest; no key without a mask, as before)
    record = None if data_mask is None else dict(data_mask=hashlib.sha1(
        np.packbits(np.asarray(data_mask, bool)).tobytes() + repr(np.shape(data_mask)).encode()).hexdigest())
    shape = seq[0].shape
    if mesh is None and element_size is None and register_kwargs.get("strategy", "auto") == "auto":
        # the element size register would pick for frame 0 (speckle-sized, femreg.pyramid.default_settings; a
        # fan's from its largest rectangle without fill)
        part = seq[0] if crop is None or crop.rectangle is None else np.asarray(seq[0])[crop.rectangle]
        element_size = tuple(default_settings(shape, spacing, speckle_statistics(part, spacing),
                                              **element_rule(regularizer)).element_size)
    check_element_size(element_size, spacing, mesh)
    fe_mesh = roi_mesh(shape, spacing, origin, element_size=element_size, margin=margin) if mesh is None \
        else as_quad_mesh(mesh)
    if isinstance(alpha, str):          # alpha="auto": chosen on the first pair, reused (femreg.autoalpha)
        from .autoalpha import choose_alpha
        # with the fan's mask, as every pair is then registered (femreg.autoalpha.pixel_image_term, fan_nodes)
        alpha = choose_alpha(seq[0], seq[1], spacing=spacing, origin=origin, regularizer=regularizer, alpha=alpha,
                             mesh=fe_mesh, progress=progress, **register_kwargs).alpha
    frame_kwargs = dict(spacing=spacing, origin=origin)
    return _run(seq, frame_kwargs, fe_mesh, crop, regularizer=regularizer, alpha=alpha, mode=mode, grid=grid,
                init=init, checkpoint_dir=checkpoint_dir, resume=resume, progress=progress, min_ncc=min_ncc,
                on_frame=on_frame, register_kwargs=register_kwargs, record=record, uncut=uncut)


def _track_beam(seq, geometry, *, spacing, origin, regularizer, alpha, mode, grid, init, mesh, element_size, margin,
                checkpoint_dir, resume, progress, min_ncc, on_frame, roi, depth, check_orientation,
                register_kwargs) -> SequenceResult:
    """:func:`track` of convex / sector frames (n_samples, n_rays): each pair registered by
    :func:`femreg.geometry.register_beam`, the frame-0 mesh that of the first pair (physical, over the echo region
    of frames 0 and 1), every later increment on that mesh moved by S_k (eq:IR on frame k's samples, as
    ``grid="current"``), the results :class:`femreg.geometry.BeamResult` in physical coordinates."""
    if grid != "current":
        raise InputError(pass_as(f"grid='reference' is not supported with a {geometry.kind} geometry (the "
                                 "increments are registered on each frame's own samples, grid='current')",
                                 f"--grid reference is not supported with --geometry {geometry.kind} (the increments "
                                 "are registered on each frame's own samples, --grid current)"))
    dr, r0 = beam_spacing(spacing, geometry, origin)
    _, sp_s, _ = sample_space(geometry, seq[0].shape, dr, r0)
    if check_orientation:           # in sample space, where the frame is a linear image (femreg.geometry)
        orientation.check(seq[0], sp_s)
    register_kwargs["check_orientation"] = False    # checked once, above
    # the first pair's registration makes the mesh (element size, echo region); later ones reuse it
    first = dict(roi=roi, depth=depth, element_size=element_size, margin=margin)
    frame_kwargs = dict(spacing=dr, origin=(r0, 0.0), geometry=geometry)
    if isinstance(alpha, str):      # alpha="auto": chosen on the first pair, reused (femreg.autoalpha)
        from .autoalpha import choose_alpha
        from .strategy import effective_regularizer_options, fresh_regularizer

        # the grid is centred on the default alpha of the beam's physical solve (times beam_alpha_factor)
        opts = effective_regularizer_options(register_kwargs.get("strategy", "auto"), regularizer,
                                             register_kwargs.get("regularizer_options"))
        base = fresh_regularizer(regularizer, None, opts).alpha * (
            default_beam_alpha_factor(seq[0], dr, sp_s[1]) if isinstance(regularizer, str) else 1.0)
        alpha = choose_alpha(seq[0], seq[1], regularizer=regularizer, alpha=alpha, base_alpha=base,
                             image_term=beam_image_term, progress=progress,
                             mesh=None if mesh is None else as_quad_mesh(mesh),
                             **frame_kwargs, **first, **register_kwargs).alpha
    return _run(seq, frame_kwargs, None if mesh is None else as_quad_mesh(mesh), None, regularizer=regularizer,
                alpha=alpha, mode=mode, grid=grid, init=init, checkpoint_dir=checkpoint_dir, resume=resume,
                progress=progress, min_ncc=min_ncc, on_frame=on_frame, register_kwargs=register_kwargs, first=first,
                record=dict(geometry=geometry.to_dict(), region=[first[k] for k in ("roi", "depth", "element_size",
                                                                                       "margin")]))


def _frame_result(r, mesh, u):
    """Frame 0 -> k: the increment's registration ``r`` (its verdict, timings, ...) with the accumulated nodal
    field ``u`` on the frame-0 ``mesh``."""
    kw = dict(shape=r.shape, spacing=r.spacing, origin=r.origin, regularizer=r.regularizer, alpha=r.alpha,
              success=r.success, status=r.status, message=r.message, nit=r.nit, energy_history=r.energy_history,
              ncc_before=r.ncc_before, ncc_after=r.ncc_after, timings=r.timings, blockmatch=r.blockmatch,
              solver_result=r.solver_result, quality=r.quality, strategy=r.strategy,
              alpha_effective=r.alpha_effective, lambda_bar=getattr(r, "lambda_bar", None),
              started_afresh=r.started_afresh)
    if isinstance(r, BeamResult):
        # the first pair's sample-space echo crop (femreg.geometry.register_beam) is said by the frame too
        return BeamResult(mesh, u, geometry=r.geometry, sample_space=r.sample_space, excluded=r.excluded, **kw)
    return RegistrationResult(mesh, u, **kw)


def _increment(seq, k, initial, S, fe_mesh, frame_kwargs, where, regularizer, alpha, inc_kwargs):
    """The increment u_k of eq:IR from frame k - 1 to k started from ``initial``: (frame 0 -> k result, the
    increment (2 n_nodes,) mm)."""
    r_inc = register(seq[k - 1], seq[k], regularizer=regularizer, alpha=alpha, initial=initial, **frame_kwargs,
                     **where, **inc_kwargs)
    inc = r_inc.u.copy()
    return _frame_result(r_inc, r_inc.mesh if fe_mesh is None else fe_mesh, S + inc), inc


def _run(seq, frame_kwargs, fe_mesh, crop, *, regularizer, alpha, mode, grid, init, checkpoint_dir, resume, progress,
         min_ncc, on_frame, register_kwargs, first=None, record=None, uncut=None) -> SequenceResult:
    """The frame loop of :func:`track`: ``frame_kwargs`` place the frames (spacing, origin, geometry), ``fe_mesh``
    the frame-0 mesh (None: the first pair's registration makes it, with the options ``first``), ``crop`` the
    echo rectangle the frames were cut to (or None); ``record`` more parameters for ``track.json``; ``uncut``
    a user's data_mask (bool, the frames' shape) on frames not cut to it: the results' ``data_mask``."""
    shape = seq[0].shape
    first = first or {}
    spacing, origin = frame_kwargs["spacing"], frame_kwargs["origin"]
    params = _params_record(len(seq), shape, spacing, origin, mode, regularizer, alpha, fe_mesh, init)
    # every other registration setting too, so a resume with different settings is refused
    params["grid"] = grid
    params["register_kwargs"] = json.loads(json.dumps({k: v for k, v in register_kwargs.items()
                                                       if k not in ("check_orientation", "data_mask")},
                                                      sort_keys=True, default=repr))
    if crop is not None:
        params["roi"] = list(crop.roi_mm)
    params.update(json.loads(json.dumps(record or {}, default=repr)))

    fresh = checkpoint_dir is not None and not (Path(checkpoint_dir) / "track.json").exists()
    existed = checkpoint_dir is not None and Path(checkpoint_dir).exists()
    described = _region_record(shape, origin, crop)
    if resume and not fresh and crop is None and "geometry" in (record or {}):
        # a beam track's region was recorded after its first pair (_record_beam_region): a resume keeps it
        old = json.loads((Path(checkpoint_dir) / "track.json").read_text()).get("registered_region")
        described["registered_region"] = old or described["registered_region"]
    ckpt = open_run_folder(checkpoint_dir, params, resume=resume, record="track.json", started=("frame_*.npz",),
                           kind="a tracking run", argument="checkpoint_dir", described=described)

    inc_kwargs = dict(register_kwargs)
    if (mode == "accumulate" and register_kwargs.get("strategy", "auto") == "auto" and isinstance(regularizer, str)
            and regularizer.startswith("momentum")):
        inc_kwargs["regularizer_options"] = dict(register_kwargs.get("regularizer_options") or {})
        inc_kwargs["regularizer_options"].setdefault("hourglass", TRACK_HOURGLASS)
    # frames written twice: frame k - 1's field kept (frame 1 is refused by track: it has no earlier field)
    repeats = set(k for k in repeated_frames(seq) if k >= 2)
    out = SequenceResult(mode=mode)
    S = 0.0                             # the accumulated field S_k (nodal, frame-0 mesh)
    prev_inc = None
    tainted = None                      # (frame, why) of the first flagged increment, accumulate mode
    prev_own_flag = ""                  # the last increment's own flag: a fresh start follows it, not a taint
    beam_excluded = None                # what the first pair of a beam track left out of the mesh
    bar = progress_bar(progress, len(seq) - 1, f"track ({mode})", "frame", on_frame)
    try:
        for k in range(1, len(seq)):
            path = None if ckpt is None else ckpt / f"frame_{k:03d}.npz"
            retried = ""
            if resume and path is not None and path.exists():
                res = load_result(path)
                inc, flag, retried = load_frame_record(path)
                computed = False
                if beam_excluded is None and isinstance(res, BeamResult):
                    beam_excluded = res.excluded
            elif k in repeats:
                # nothing moved between frames k - 1 and k: frame 0 -> k is frame 0 -> k - 1
                res = copy.copy(out[-1])
                note = repeat_note(k)
                res.message = f"{res.message}; {note}" if res.message else note
                res.repeats = k - 1     # for on_frame (not saved: the message says it in the file)
                inc, flag, computed = np.zeros_like(np.asarray(out.increments[-1], float)), out.flags[-1], True
                if path is not None:
                    save_frame(path, res, inc, flag, k, mode)
            else:
                # the first pair makes the mesh when there is none yet (convex / sector frames), later ones reuse it
                where = dict(first) if fe_mesh is None else dict(roi=None, depth=None) if first else {}
                if mode == "direct":
                    res = register(seq[0], seq[k], regularizer=regularizer, alpha=alpha, mesh=fe_mesh,
                                   **frame_kwargs, **where, **register_kwargs)
                    inc = res.u.copy()
                else:
                    fresh = init == "blockmatch" or prev_inc is None or bool(prev_own_flag)
                    # a fresh start is the strategy's own (pyramid with "auto"), or the paper's block matching
                    fresh_start = "blockmatch" if init == "blockmatch" else None
                    if fe_mesh is None:
                        where.update(mesh=None)
                    elif grid == "current":
                        # frame k's pixel grid, mesh moved with the tissue: I_k is never interpolated
                        where.update(mesh=fe_mesh if k == 1 else MeshQuad1(fe_mesh.p + S.reshape(-1, 2).T, fe_mesh.t),
                                     allow_mesh_outside=True)
                    else:
                        where.update(mesh=fe_mesh, offset=S if k > 1 else None)
                    # the previous increment unless the frames match better with no motion (a still frame after a
                    # moving one: femreg.initial.Previous); not on convex / sector frames (their own register)
                    previous = prev_inc if prev_inc is None or "geometry" in frame_kwargs else \
                        Previous(prev_inc, fresh_start)
                    # flagged from the previous increment: registered again from the fresh start
                    res, inc, retried = retry_flagged(
                        lambda initial: _increment(seq, k, initial, S, fe_mesh, frame_kwargs, where, regularizer,
                                                   alpha, inc_kwargs), previous, fresh_start, fresh, min_ncc, k)
                if crop is not None:
                    crop.widen(res)
                elif uncut is not None:
                    res.data_mask = uncut
                if crop is None and isinstance(res, BeamResult):
                    # a beam track's mesh is the first pair's, cut by its echo crop: every frame says so
                    if beam_excluded is None:
                        beam_excluded = res.excluded
                        if ckpt is not None and res.excluded:
                            _record_beam_region(ckpt / "track.json", res)
                    elif res.excluded is None:
                        res.excluded = beam_excluded
                        res.message = f"{res.message}; {beam_excluded}" if res.message else beam_excluded
                if tainted is not None:
                    mark_tainted(res, *tainted)
                # A pair is flagged by image evidence, or when the registration's own check failed.
                flag = frame_flag(res, min_ncc)
                computed = True
                if path is not None:
                    save_frame(path, res, inc, flag, k, mode, retried)
            if fe_mesh is None:         # the first pair's mesh: every later frame's
                fe_mesh = res.mesh
            S = np.asarray(res.u, float).copy() if mode == "accumulate" else S
            if retried:
                out.retried.append(k)
                res.retried = retried   # for on_frame (the file keeps it as "retried")
            if k in repeats:
                out.repeated.append(k)
            else:                       # a repeat's zero increment is no guess for the next one
                prev_inc = inc
            own = own_flag(res, flag, min_ncc)
            if own and mode == "accumulate" and tainted is None:
                tainted = (k, own)      # every later frame adds this increment
            if k not in repeats:
                # a retried increment's start from the previous one failed: the next starts fresh as well
                prev_own_flag = own or retried
            out.append(res)
            out.increments.append(inc)
            out.flags.append(flag)
            out.computed.append(computed)
            if on_frame is not None:
                on_frame(k, res, flag)
            if bar is not None:
                bar.set_postfix_str(f"ncc {res.ncc_after:.2f}" + (" FLAGGED" if flag else ""))
                bar.update(1)
    except InputError:
        # bad input found by the first pair (a convex / sector track's region is checked there): no run was
        # started, so the record this call wrote goes too and the folder is left as it was
        if fresh and ckpt is not None and not any(ckpt.glob("frame_*.npz")):
            (ckpt / "track.json").unlink(missing_ok=True)
            if not existed and not any(ckpt.iterdir()):
                ckpt.rmdir()
        raise
    finally:
        if bar is not None:
            bar.close()
    return out


def load_track(checkpoint_dir) -> SequenceResult:
    """Read every ``frame_KKK.npz`` of a tracking folder (written by :func:`track` / ``femreg track``)."""
    ckpt = Path(checkpoint_dir)
    pfile = ckpt / "track.json"
    if not pfile.exists():
        raise InputError(f"{ckpt}: not a femreg track folder (no track.json)")
    params = json.loads(pfile.read_text())
    out = SequenceResult(mode=params.get("mode", "accumulate"))
    for k in range(1, int(params["n_frames"])):
        path = ckpt / f"frame_{k:03d}.npz"
        if not path.exists():
            break
        out.append(load_result(path))
        with np.load(path, allow_pickle=False) as z:
            out.increments.append(np.asarray(z["increment"], float))
            out.flags.append(str(z["flag"]))
            if "retried" in z.files:
                out.retried.append(k)
        out.computed.append(False)
    return out
