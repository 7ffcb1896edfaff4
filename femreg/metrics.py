"""The paper's accuracy and contrast metrics (arXiv:2508.19086, "Results": displacement / strain % errors, SR,
CNR_e; the elastographic contrast-to-noise ratio after T. Varghese, J. Ophir, Ultrasound Med. Biol. 24(6):915-924,
1998).

Errors are integrated over the FE mesh domain with Gauss quadrature on the mesh (``intorder``, default
:data:`femreg.quadrature.GAUSS_3X3`, 3 x 3 points per quad), comparing the measured FE field with a true field given as a callable:

    Disp. error_i   = ||u^t_i - u^m_i|| / ||u^t_i||            (i = x, y), total with the vector norm,
    Strain error_ij = ||e^t_ij - e^m_ij|| / ||e^t_ij||         (ij = xx, yy, xy), total with e : e
                      (the Frobenius inner product counts the shear twice: e:e = exx^2 + eyy^2 + 2 exy^2).

All values are fractions (multiply by 100 for %).

Contrast: SR = eps_A / eps_B, CNR_e = 2 (eps_A - eps_B)^2 / (eta_A^2 + eta_B^2), with eps the mean axial strain
and eta^2 its variance outside (A) and inside (B) the inclusion ROI.
"""
from __future__ import annotations

import numpy as np

from .fields import strain_components
from .quadrature import GAUSS_3X3

__all__ = ["field_errors", "strain_ratio", "cnr_e", "contrast_metrics", "mesh_quadrature"]


def mesh_quadrature(mesh, intorder: int = GAUSS_3X3):
    """Quadrature points (n, 2) mm and weights (n,) mm^2 over the mesh, plus a skfem vector basis."""
    from skfem import Basis, ElementQuad1, ElementVector

    basis = Basis(mesh, ElementVector(ElementQuad1()), intorder=intorder)
    X = basis.mapping.F(basis.X)                      # (2, n_el, n_qp)
    pts = np.column_stack([X[0].ravel(), X[1].ravel()])
    w = basis.dx.ravel()
    return pts, w, basis


def _measured(result_or_u, mesh, basis):
    """Measured u (2, n_el, n_qp) and grad u (2, 2, n_el, n_qp) at the basis' quadrature points."""
    u = getattr(result_or_u, "u", result_or_u)
    f = basis.interpolate(np.asarray(u, float))
    return np.asarray(f), np.asarray(f.grad)


def field_errors(result, true_displacement, true_strain=None, *, mesh=None, intorder: int = GAUSS_3X3) -> dict:
    """Relative L2 errors of a registration against a known field, integrated over the FE mesh.

    Parameters
    ----------
    result : RegistrationResult or (2 n_nodes,) nodal vector (then ``mesh`` is required)
    true_displacement : callable (n, 2) mm -> (n, 2) mm
    true_strain : callable (n, 2) -> (n, 3) [exx, eyy, exy], optional
        Default: central differences of ``true_displacement`` (step 1e-4 mm).

    Returns
    -------
    dict with fractions: ``ux, uy, u`` (displacement) and ``exx, eyy, exy, e`` (strain).
    """
    mesh = getattr(result, "mesh", mesh)
    if mesh is None:
        raise ValueError("field_errors needs result.mesh or mesh=")
    pts, w, basis = mesh_quadrature(mesh, intorder)
    val, grad = _measured(result, mesh, basis)
    um = np.column_stack([val[0].ravel(), val[1].ravel()])
    em = strain_components(grad).reshape(-1, 3)
    ut = np.asarray(true_displacement(pts), float)
    if true_strain is not None:
        et = np.asarray(true_strain(pts), float)
    else:
        h = 1e-4
        ex = (np.asarray(true_displacement(pts + [h, 0])) - np.asarray(true_displacement(pts - [h, 0]))) / (2 * h)
        ey = (np.asarray(true_displacement(pts + [0, h])) - np.asarray(true_displacement(pts - [0, h]))) / (2 * h)
        et = strain_components(np.stack([np.stack([ex[:, 0], ey[:, 0]]), np.stack([ex[:, 1], ey[:, 1]])]))

    def rel(d, t, c=None):
        c = np.ones(d.shape[1]) if c is None else np.asarray(c)
        num = np.sum(w[:, None] * c * d ** 2)
        den = np.sum(w[:, None] * c * t ** 2)
        return float(np.sqrt(num / den)) if den > 0 else float("inf")

    du, de = um - ut, em - et
    out = {"ux": rel(du[:, :1], ut[:, :1]), "uy": rel(du[:, 1:], ut[:, 1:]), "u": rel(du, ut),
           "exx": rel(de[:, :1], et[:, :1]), "eyy": rel(de[:, 1:2], et[:, 1:2]), "exy": rel(de[:, 2:], et[:, 2:]),
           "e": rel(de, et, [1.0, 1.0, 2.0])}
    return out


def _split(values, inside, weights=None):
    v = np.asarray(values, float).ravel()
    m = np.asarray(inside, bool).ravel()
    w = np.ones_like(v) if weights is None else np.asarray(weights, float).ravel()
    ok = np.isfinite(v)
    a, b = ok & ~m, ok & m
    if not a.any() or not b.any():
        raise ValueError("ROI mask must leave finite samples both inside and outside")
    mean = lambda s: float(np.sum(w[s] * v[s]) / np.sum(w[s]))  # noqa: E731
    var = lambda s, mu: float(np.sum(w[s] * (v[s] - mu) ** 2) / np.sum(w[s]))  # noqa: E731
    ea, eb = mean(a), mean(b)
    return ea, eb, var(a, ea), var(b, eb)


def strain_ratio(exx, inside, weights=None) -> float:
    """SR = mean exx outside the ROI / mean exx inside (``inside`` a boolean mask of the samples)."""
    ea, eb, _, _ = _split(exx, inside, weights)
    return ea / eb


def cnr_e(exx, inside, weights=None) -> float:
    """CNR_e = 2 (eps_A - eps_B)^2 / (eta_A^2 + eta_B^2), eta^2 the variances outside (A) / inside (B)."""
    ea, eb, va, vb = _split(exx, inside, weights)
    return 2.0 * (ea - eb) ** 2 / (va + vb)


def contrast_metrics(result, roi, *, intorder: int = GAUSS_3X3) -> dict:
    """SR and CNR_e of a registration, integrated over the mesh; ``roi`` callable (n, 2) mm -> (n,) bool
    (True inside the inclusion ROI), or a boolean (n_axial, n_lateral) mask on the reference pixel grid."""
    if callable(roi):
        pts, w, basis = mesh_quadrature(result.mesh, intorder)
        _, grad = _measured(result, result.mesh, basis)
        exx = grad[0, 0].ravel()
        inside = np.asarray(roi(pts), bool)
    else:
        exx = result.on_grid()["exx"]
        inside = np.asarray(roi, bool)
        if inside.shape != exx.shape:
            raise ValueError(f"ROI mask shape {inside.shape} != image shape {exx.shape}")
        w = None
    return {"SR": strain_ratio(exx, inside, w), "CNR_e": cnr_e(exx, inside, w)}
