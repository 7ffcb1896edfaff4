"""Quality measures that need no ground truth (real scanner data).

* :func:`image_energy` -- the image term psi of eq:IR (sum of squared differences, pixel midpoint rule) at the
  result, at u = 0 and at the block-matching initial guess: how much of the image mismatch the registration
  explains.
* :func:`strain_snr` -- elastographic SNR of the axial strain in a window, ``SNR_e = |mean| / std``.
* :func:`hourglass` -- RMS amplitude of the element-wise checkerboard (hourglass) mode of the nodal
  displacement, the spurious pattern a regulariser that does not see it leaves to the (weak) data term.
* :func:`consistency` -- RMS difference of two displacement fields on the pixel grid (e.g. accumulated
  1 -> 2 -> 3 by eq:IR versus direct 1 -> 3) and of their axial strains.
* :func:`mesh_dependence` -- relative RMS difference of the strain images of one pair registered on two meshes
  offset by a fraction of an element: what of a strain image belongs to the mesh (mesh-aligned blocks,
  staircasing of the TV regularisers along element lines) rather than to the tissue.

NCC of reference vs warped moving image before and after is on the result itself
(:attr:`femreg.RegistrationResult.ncc_before` / ``ncc_after``).

Windows are ``((x0, x1), (y0, y1))`` in mm: axial range, lateral range; a pixel belongs to the window when its
centre lies in the closed box.
"""
from __future__ import annotations

import numpy as np

from .data_term import SSDTerm
from .errors import InputError, counted
from .image import SplineImage, normalize_pair, pixel_axes, validate_image
from .pixels import PixelQuadrature
from .registration import ncc, nodal_values

__all__ = ["image_energy", "window_mask", "strain_snr", "consistency", "hourglass", "mesh_dependence"]


def image_energy(result, reference_image, moving_image, *, normalize: bool = True) -> dict:
    """Image term psi (eq:IR) of a two-frame result at u = 0, at its block-matching guess and at the result.

    Parameters
    ----------
    result : RegistrationResult
        From :func:`femreg.register` on ``reference_image`` / ``moving_image`` (no sequence offset).
    reference_image, moving_image : (n_axial, n_lateral) array
        The pair that was registered (same grid as ``result``).
    normalize : bool
        Normalise each image (minus its mean, over its spread: :func:`femreg.image.normalize_pair`), as :func:`femreg.register` does by default, so that psi is the
        number the solver minimised.

    Returns
    -------
    dict
        ``psi_zero``, ``psi_initial`` (NaN when the result holds no block-matching field), ``psi_final`` (in
        normalised intensity^2 mm^2), ``reduction = 1 - psi_final / psi_zero``, ``reduction_vs_initial =
        1 - psi_final / psi_initial`` and ``ncc_initial`` (NCC at the block-matching guess).
    """
    ref = validate_image(reference_image, "reference image")
    mov = validate_image(moving_image, "moving image")
    if ref.shape != tuple(result.shape) or mov.shape != ref.shape:
        raise InputError(f"images {ref.shape} / {mov.shape} do not match the result grid {tuple(result.shape)}")
    if normalize:
        ref, mov, _ = normalize_pair(ref, mov)
    quad = PixelQuadrature(result.mesh, result.shape, result.spacing, result.origin, locator=result.locator)
    term = SSDTerm(quad, SplineImage(ref, result.spacing, result.origin),
                   SplineImage(mov, result.spacing, result.origin))
    n_dof = result.u.size
    psi0 = term.energy(np.zeros(n_dof))
    psi1 = term.energy(np.asarray(result.u, float))
    if result.blockmatch is not None:
        u_bm = nodal_values(result.blockmatch, result.mesh, "initial")
        psi_bm = term.energy(u_bm)
        ncc_bm = ncc(term.warped_moving(u_bm), term.ref_values)
    else:
        psi_bm = ncc_bm = float("nan")
    return {"psi_zero": psi0, "psi_initial": psi_bm, "psi_final": psi1,
            "reduction": 1.0 - psi1 / psi0 if psi0 > 0 else float("nan"),
            "reduction_vs_initial": 1.0 - psi1 / psi_bm if psi_bm > 0 else float("nan"),
            "ncc_initial": ncc_bm}


def window_mask(shape, spacing, origin, window) -> np.ndarray:
    """Boolean (n_axial, n_lateral) mask of the pixels whose centres lie in ``window`` ((x0, x1), (y0, y1)) mm."""
    w = np.asarray(window, float)
    if w.shape != (2, 2) or not np.all(np.isfinite(w)) or np.any(w[:, 1] <= w[:, 0]):
        raise InputError(f"window must be ((x0, x1), (y0, y1)) mm with x0 < x1 and y0 < y1, got {window!r}")
    x, y = pixel_axes(tuple(shape), np.asarray(spacing, float), np.asarray(origin, float))
    mx = (x >= w[0, 0]) & (x <= w[0, 1])
    my = (y >= w[1, 0]) & (y <= w[1, 1])
    return mx[:, None] & my[None, :]


def strain_snr(result, window, component: str = "exx") -> dict:
    """Elastographic SNR ``|mean| / std`` of a strain component in a window (no ground truth needed).

    Parameters
    ----------
    result : RegistrationResult (or anything with ``on_grid()``, ``shape``, ``spacing``, ``origin``)
    window : ((x0, x1), (y0, y1)) mm
    component : {"exx", "eyy", "exy"}

    Returns
    -------
    dict
        ``mean``, ``std`` (population), ``snr`` and ``n`` (pixels inside both the window and the mesh).
    """
    if component not in ("exx", "eyy", "exy"):
        raise InputError(f"component must be 'exx', 'eyy' or 'exy', got {component!r}")
    e = result.on_grid()[component]
    vals = e[window_mask(result.shape, result.spacing, result.origin, window) & np.isfinite(e)]
    if vals.size < 2:
        raise InputError(f"window {window!r} holds {counted(vals.size, 'pixel')} of the mesh; need at least 2")
    mean, std = float(np.mean(vals)), float(np.std(vals))
    return {"mean": mean, "std": std, "snr": abs(mean) / std if std > 0 else float("inf"), "n": int(vals.size)}


def consistency(a, b, window=None) -> dict:
    """RMS difference of two results on one pixel grid (e.g. accumulated vs direct frame 1 -> 3).

    Parameters
    ----------
    a, b : RegistrationResult
        Same ``shape``, ``spacing`` and ``origin``; compared where both are defined (inside both meshes).
    window : ((x0, x1), (y0, y1)) mm, optional
        Restrict the comparison to a window.

    Returns
    -------
    dict
        ``rms_du`` (mm, RMS of ``|u_a - u_b|``), ``rms_u`` (mm, RMS of ``|u_b|``, the scale), ``rms_dexx``
        (RMS of the axial-strain difference), ``rms_exx`` (RMS of b's axial strain), ``n`` (pixels).
    """
    if tuple(a.shape) != tuple(b.shape) or not np.allclose(a.spacing, b.spacing) or \
            not np.allclose(a.origin, b.origin):
        raise InputError(f"results are on different pixel grids: {tuple(a.shape)} vs {tuple(b.shape)}")
    ga, gb = a.on_grid(), b.on_grid()
    ok = np.isfinite(ga["ux"]) & np.isfinite(gb["ux"]) & np.isfinite(ga["exx"]) & np.isfinite(gb["exx"])
    if window is not None:
        ok &= window_mask(a.shape, a.spacing, a.origin, window)
    if not ok.any():
        raise InputError("the two results share no pixel (or none in the window)")
    du2 = (ga["ux"] - gb["ux"]) ** 2 + (ga["uy"] - gb["uy"]) ** 2
    return {"rms_du": float(np.sqrt(np.mean(du2[ok]))),
            "rms_u": float(np.sqrt(np.mean((gb["ux"] ** 2 + gb["uy"] ** 2)[ok]))),
            "rms_dexx": float(np.sqrt(np.mean((ga["exx"] - gb["exx"])[ok] ** 2))),
            "rms_exx": float(np.sqrt(np.mean(gb["exx"][ok] ** 2))),
            "n": int(ok.sum())}


def hourglass(result) -> dict:
    """RMS amplitude of the hourglass (checkerboard) mode of a bilinear-quad displacement.

    For each element with corners 0..3 in order around it, ``h = (u_0 - u_1 + u_2 - u_3) / 4`` is the
    coefficient of the mode that alternates sign from corner to corner: it vanishes for an affine field and is of
    order ``h_x h_y |d2u/dxdy| / 4`` for a smooth one, but equals the amplitude of a node-to-node checkerboard.

    Returns
    -------
    dict
        ``ux``, ``uy``: RMS of h over the elements (mm), for each displacement component.
    """
    from .regularizers.momentum import hourglass_operator   # raises InputError for a mesh that is not quads

    h = (hourglass_operator(result.mesh) @ result.u / 4.0).reshape(2, -1)
    return {name: float(np.sqrt(np.mean(hc ** 2))) for name, hc in zip(("ux", "uy"), h)}


def mesh_dependence(a, b, *, step: float = 0.1, window=None, strain: str = "recovered") -> dict:
    """Relative RMS difference of the strains of two registrations of one pair whose meshes are offset.

    Register the same frames twice, the second time with the mesh moved by a fraction of an element (e.g. the
    frames cropped by a few samples and lines, ``origin`` kept in tissue coordinates), then compare here.  A
    strain pattern set by the data moves with the tissue and stays; one set by the mesh (blocks whose edges follow
    element lines, staircasing of the TV regularisers) moves with the mesh and shows in the difference.

    Measured (R_P_sigma defaults, in vivo frames 1 -> 3, full frames against frames cropped by 25 samples and 3
    lines, i.e. 0.5 mm axially and 0.6 mm laterally, about 0.7-1 element): e_xx / e_yy / e_xy 0.081 / 0.090 /
    0.125 (seq304) and 0.090 / 0.083 / 0.227 (seq299; refined, as before the refinement's spread test, 0.178 /
    0.123 / 0.229 and 0.231 / 0.125 / 0.378); simulated pairs of the robustness benchmark (stiff
    inclusion, bending, shear) 0.012 / 0.015 / 0.084 or less.  The rectangular e_xy patches of the in vivo images
    stay where they are (the difference lies in a few element-sized spots), so they are not mesh artefacts.

    Parameters
    ----------
    a, b : RegistrationResult
        The two results, in one coordinate frame (mm); their pixel grids may differ.
    step : float
        Spacing (mm) of the square grid of points the strains are compared on, inside both meshes.
    window : ((x0, x1), (y0, y1)) mm, optional
        Restrict the comparison to a window.
    strain : {"recovered", "element"}
        The strain compared (:meth:`femreg.RegistrationResult.strain`); the element strain, constant per element,
        is the blocky reference.

    Returns
    -------
    dict
        ``exx``, ``eyy``, ``exy``: ``||e_a - e_b|| / sqrt((||e_a||^2 + ||e_b||^2) / 2)`` over the points
        (0: no dependence on the mesh; about 1.4 for unrelated images); ``n`` the number of points.
    """
    step = float(step)
    if not (np.isfinite(step) and step > 0):
        raise InputError(f"step must be a finite number > 0 (mm), got {step!r}")
    lo = np.maximum(a.mesh.p.min(axis=1), b.mesh.p.min(axis=1))
    hi = np.minimum(a.mesh.p.max(axis=1), b.mesh.p.max(axis=1))
    if window is not None:
        (x0, x1), (y0, y1) = window
        lo, hi = np.maximum(lo, (x0, y0)), np.minimum(hi, (x1, y1))
    if np.any(hi - lo < step):
        raise InputError("the two meshes (and the window) share no region to compare")
    X, Y = np.meshgrid(np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step),
                       indexing="ij")
    pts = np.column_stack([X.ravel(), Y.ravel()])
    ea, eb = a.strain(pts, strain), b.strain(pts, strain)
    ok = np.all(np.isfinite(ea), axis=1) & np.all(np.isfinite(eb), axis=1)
    if not ok.any():
        raise InputError("the two results share no point where both strains are defined")
    out = {}
    for k, name in enumerate(("exx", "eyy", "exy")):
        da, db = ea[ok, k], eb[ok, k]
        scale = np.sqrt(0.5 * (np.sum(da ** 2) + np.sum(db ** 2)))
        out[name] = float(np.sqrt(np.sum((da - db) ** 2)) / scale) if scale > 0 else 0.0
    out["n"] = int(ok.sum())
    return out
