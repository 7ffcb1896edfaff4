"""``femreg register`` / ``femreg track`` on volumes: an ``.npz`` whose ``spacing`` holds three values (dx, dy,
dz mm) and whose ``rf`` (or only) array is a volume (n_x, n_y, n_z) or a volume sequence (n_frames, n_x, n_y,
n_z); a MetaImage of NDims 4 or a MAT-file whose spacing has three values; with ``--volume`` any file
:func:`femreg.io.read_volumes` reads (a MetaImage of NDims 3 as one volume)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..errors import InputError
from ._common import frame_index, volumes_only

__all__ = ["read_volume_file", "register_volumes", "track_volumes"]

#: register options passed on to volumes separately (a swept probe's geometry)
_NOT_FOR_VOLUMES = ("geometry",)


def read_volume_file(path, *, volume: bool = False, origin=None, spacing=None, variable=None,
                     check_sampling: bool = True):
    """``(array, spacing (3,), origin (3,))`` when ``path`` holds RF volumes, else None: an .npz whose spacing has 3
    values; a file that can only hold volumes (a MetaImage of NDims 4, a MAT-file whose spacing has 3 values);
    with ``volume`` (CLI ``--volume``) any file :func:`femreg.io.read_volumes` reads, a 3D array one volume
    (axial, lateral, elevational), e.g. a MetaImage of NDims 3, which is otherwise read as a stack of frames.
    ``origin``: the frames' ``--origin``, refused for volumes (their origin comes from the file); ``spacing``:
    ``--spacing DX DY DZ`` (mm; "auto" / None entries keep the file's), overriding the file's; ``variable``:
    ``--variable``, the array's name; ``check_sampling``: unless ``--no-orientation-check``, a given axial spacing
    held against the file's sampling rate (:func:`femreg.io.read_volumes`)."""
    got = _read_volume_file(Path(path), volume, spacing, variable, check_sampling)
    if got is not None and origin is not None:
        raise InputError(f"{path}: --origin places a frame's first sample; a volume's origin comes from its file "
                         "(key or variable 'origin', three values in mm)")
    return got


def _read_volume_file(p: Path, volume: bool, spacing=None, variable=None, check_sampling: bool = True):
    """:func:`read_volume_file` without its ``origin`` check."""
    if spacing is not None and len(spacing) != 3 and (volume or volumes_only(p)):
        raise InputError(f"{p}: volumes take --spacing DX DY DZ (axial, lateral, elevational, mm), got "
                         f"{len(spacing)} values")
    if volume or volumes_only(p):
        from ..io import read_volumes

        v = read_volumes(p, spacing=spacing, variable=variable, check_sampling=check_sampling)
        arr = v.frames[0] if v.n_frames == 1 else v.frames
        return arr, np.asarray(v.spacing, float).ravel(), np.asarray(v.origin, float).ravel()
    if p.suffix.lower() != ".npz" or not p.exists():
        return None
    try:
        z = np.load(p, allow_pickle=False)
    except (OSError, ValueError):
        return None
    with z:
        if "spacing" not in z or np.size(z["spacing"]) != 3:
            return None
        key = "rf" if "rf" in z else next((k for k in z.files if k not in ("spacing", "origin")), None)
        if key is None:
            raise InputError(f"{p}: no volume array in the file")
        arr = np.asarray(z[key])
        if arr.ndim not in (3, 4):
            raise InputError(f"{p}: spacing has 3 values but {key!r} has shape {arr.shape}; a volume is "
                             f"(n_x, n_y, n_z), a volume sequence (n_frames, n_x, n_y, n_z)")
        origin = np.asarray(z["origin"], float).ravel() if "origin" in z else np.zeros(3)
        if origin.size != 3:
            origin = np.zeros(3)
        sp = np.asarray(z["spacing"], float).ravel()
        if spacing is not None:         # --spacing DX DY DZ over the file's ('auto' keeps its value)
            if len(spacing) != 3:
                raise InputError(f"{p}: volumes take --spacing DX DY DZ (axial, lateral, elevational, mm), got "
                                 f"{len(spacing)} values")
            sp = np.array([sp[k] if v is None else float(v) for k, v in enumerate(spacing)])
        return arr, sp, origin


def _kwargs(kw):
    return {k: v for k, v in kw.items() if k not in _NOT_FOR_VOLUMES}


def register_volumes(args, vol, kw) -> int:
    """The register command on a volume file (``vol`` from :func:`read_volume_file`)."""
    import femreg

    arr, spacing, origin = vol
    if args.moving is None:
        if arr.ndim != 4:
            raise InputError(f"{args.reference}: one volume; give MOVING, or a file holding a volume sequence")
        i, j = args.pair or (0, 1)
        ref, mov = (arr[frame_index(k, arr.shape[0], args.reference, "--pair")] for k in (i, j))
    else:
        other = read_volume_file(args.moving, volume=True, spacing=getattr(args, "spacing", None),
                                 variable=getattr(args, "variable", None),
                                 check_sampling=not getattr(args, "no_orientation_check", False))
        if not np.allclose(other[1], spacing):
            raise InputError(f"spacing differs between volumes: {tuple(spacing)} vs {tuple(other[1])}")
        i, j = args.pair or (0, 0)
        ref = arr if arr.ndim == 3 else arr[frame_index(i, arr.shape[0], args.reference, "--pair")]
        mov = other[0] if other[0].ndim == 3 else other[0][frame_index(j, other[0].shape[0], args.moving, "--pair")]
    if not str(args.output).endswith(".npz"):
        raise InputError(f"-o must name a .npz file, got {args.output}")
    from ..autoalpha import showing_progress

    try:
        with showing_progress(not getattr(args, "no_progress", False)):
            res = femreg.register(ref, mov, spacing=spacing, origin=origin, geometry=kw.get("geometry"),
                                  **_kwargs(kw))
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - a computation that fails is a failed pair (1)
        print(f"femreg register: failed: the registration stopped ({type(exc).__name__}: {exc})", file=sys.stderr)
        return 1
    res.save(args.output)
    # the frames' one line (femreg.cli.register_cmd), not the library's repr
    print(f"pair: ncc {res.ncc_before:.3f} -> {res.ncc_after:.3f}, nit {res.nit}, {res.mesh.p.shape[1]} nodes, "
          f"regularizer {res.regularizer}, alpha {res.alpha:g}" + (f"; {res.message}" if res.success else ""))
    if res.excluded:
        print(f"femreg register: left out of the mesh (the rest is registered): {res.excluded}")
    print(f"wrote {args.output}")
    if not res.success:
        reason = res.message.removeprefix("FAILED: ")
        print(f"femreg register: failed: the registration failed its checks: {reason}{_exchanged_hint(spacing)}",
              file=sys.stderr)
        return 1
    return 0


def _exchanged_hint(spacing) -> str:
    """A failed volume's hint where the lateral and elevational spacings differ: the carrier checks only the axial
    one, and the speckle cannot tell them apart before registering (benchmarks/volume_spacing_swap.py: exchanged,
    the elevational over lateral cell aspect of the 7 MHz matrix probe reads 1.41, of a 3.5 MHz swept probe 0.97,
    where right volumes of other probes read 0.71-3.16); the 7 MHz matrix loop of benchmarks/volume_tgc.py given
    ``DX DZ DY`` failed on peak hopping (NCC after 0.54) where ``DX DY DZ`` registers at 0.96."""
    dx, dy, dz = (float(v) for v in spacing)
    if max(dy, dz) < 1.1 * min(dy, dz):
        return ""
    return (f" (if the lateral and elevational spacings are exchanged, the order is axial, lateral, elevational: "
            f"--spacing {dx:g} {dz:g} {dy:g})")


def track_volumes(args, vol, kw) -> int:
    """The track command on a volume-sequence file (``vol`` from :func:`read_volume_file`; ``kw["geometry"]`` a
    swept probe's, else absent): ``frame_KKK.npz`` (frame 0 -> K) in the output folder as each frame finishes,
    ``--resume``, the progress bar and the exit codes of the frame track (:mod:`femreg.cli.track_cmd`)."""
    from ..volume import track_volume

    arr, spacing, origin = vol
    if arr.ndim != 4:
        raise InputError(f"{args.file}: a single volume; track needs a volume sequence (n_frames, n_x, n_y, n_z)")
    from ._common import run_tracking

    return run_tracking(args, lambda on_frame: track_volume(
        list(arr), spacing=spacing, origin=origin, mode=args.mode, checkpoint_dir=args.output, resume=args.resume,
        progress=not args.no_progress, min_ncc=args.min_ncc, on_frame=on_frame, **kw), "volume", total=len(arr) - 1)
