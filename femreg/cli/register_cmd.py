"""``femreg register REF MOVING -r NAME [--alpha A] -o OUT.npz``: two-frame registration from .npz frames.

Inputs are .npz files holding ``rf`` (2D, axial x lateral) and ``spacing`` (2,) mm, optionally ``origin``.
OUT is written by :meth:`femreg.RegistrationResult.save` (mesh, nodal u, ux/uy/exx/eyy/exy on the pixel grid).
"""
from __future__ import annotations

import os

import numpy as np


def _read_frame(path):
    from femreg.errors import FileFormatError, InputError

    if not os.path.exists(path):
        raise InputError(f"file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001
        raise FileFormatError(f"{path}: not a readable .npz file ({type(exc).__name__})") from None
    for key in ("rf", "spacing"):
        if key not in d:
            raise FileFormatError(f"{path}: missing key '{key}' (need 'rf' and 'spacing', optional 'origin')")
    return d["rf"], d["spacing"], d.get("origin", np.zeros(2))


def add_parser(subparsers):
    from femreg.regularizers import available_regularizers

    p = subparsers.add_parser("register", help="register two frames (.npz with rf, spacing)",
                              description="Two-frame FE registration of .npz frames (rf, spacing[, origin]); writes mesh, nodal u and "
                              "ux, uy, exx, eyy, exy on the reference pixel grid to OUT.npz.")
    p.add_argument("reference", help="reference frame .npz (rf, spacing[, origin])")
    p.add_argument("moving", help="moving frame .npz")
    p.add_argument("-r", "--regularizer", default="strain",
                   help=f"regulariser name (available: {', '.join(available_regularizers())})")
    p.add_argument("--alpha", type=float, default=None, help="regularisation weight (default: documented)")
    p.add_argument("--element-size", type=float, default=None, help="element size in mm (default 2, see femreg.mesh)")
    p.add_argument("--maxiter", type=int, default=20)
    p.add_argument("--tol", type=float, default=1e-3)
    p.add_argument("-o", "--output", required=True, help="output .npz")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    import femreg
    from femreg.errors import InputError

    ref, sp_ref, org_ref = _read_frame(args.reference)
    mov, sp_mov, _ = _read_frame(args.moving)
    if not np.allclose(np.ravel(sp_ref), np.ravel(sp_mov)):
        raise InputError(f"spacing differs between frames: {np.ravel(sp_ref)} vs {np.ravel(sp_mov)}")
    res = femreg.register(ref, mov, spacing=sp_ref, origin=org_ref, regularizer=args.regularizer,
                          alpha=args.alpha, element_size=args.element_size, maxiter=args.maxiter, tol=args.tol)
    res.save(args.output)
    print(f"{res}\nwrote {args.output}")
    return 0
