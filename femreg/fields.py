"""Displacement and strain of a bilinear-quad FE field, evaluated in one place.

Small strains ``exx = dux/dx``, ``eyy = duy/dy``, ``exy = (dux/dy + duy/dx) / 2`` (tensor shear), the quantity
of the paper's strain errors ("Results").  Every strain femreg reports comes from :func:`strain_components`:
at located points (:func:`sample`, used for pixel grids and arbitrary points), at element centres
(:func:`element_strains`, for meshes and ParaView) and at quadrature points (:mod:`femreg.metrics`).
Lengths in mm; ``u`` is the interleaved nodal vector ``[ux0, uy0, ux1, ...]`` (scikit-fem's vector DOF order).
"""
from __future__ import annotations

import numpy as np

from .errors import InputError
from .quadrature import ELEMENT_CENTRE_RULE

__all__ = ["FIELDS", "strain_components", "sample", "element_strains"]

#: Names of the sampled fields, in order.
FIELDS = ("ux", "uy", "exx", "eyy", "exy")


def strain_components(grad) -> np.ndarray:
    """[exx, eyy, exy] from a displacement gradient ``grad[i, j] = du_i/dx_j`` of shape (2, 2, ...);
    returns shape (..., 3)."""
    g = np.asarray(grad, float)
    return np.stack([g[0, 0], g[1, 1], 0.5 * (g[0, 1] + g[1, 0])], axis=-1)


def sample(u, location, fields=FIELDS) -> dict:
    """Fields of the nodal displacement ``u`` at located points.

    Parameters
    ----------
    u : (2 n_nodes,) mm
    location : femreg.pixels.Location
        Points inside the mesh with their element nodes ``nodes`` (m, 4), shape functions ``N`` (m, 4) and
        physical gradients ``dN`` (m, 4, 2) per mm.
    fields : names from :data:`FIELDS`

    Returns
    -------
    dict name -> (m,) float: values at the located (inside) points, in ``location``'s order.
    """
    u = np.asarray(u, float)
    ux, uy = u[0::2][location.nodes], u[1::2][location.nodes]
    out = {}
    if "ux" in fields:
        out["ux"] = np.sum(location.N * ux, axis=1)
    if "uy" in fields:
        out["uy"] = np.sum(location.N * uy, axis=1)
    if any(f in fields for f in ("exx", "eyy", "exy")):
        grad = np.stack([np.einsum("nk,nkd->dn", ux, location.dN), np.einsum("nk,nkd->dn", uy, location.dN)])
        e = strain_components(grad)
        for k, name in enumerate(("exx", "eyy", "exy")):
            if name in fields:
                out[name] = e[:, k]
    return out


def element_strains(mesh_points, mesh_cells, u) -> np.ndarray:
    """Small strains [exx, eyy, exy] at each bilinear quad's centre (reference point (1/2, 1/2)), shape (n_el, 3).

    Exact for a displacement field affine in (x, y).  ``mesh_points`` (2, n_nodes) mm, ``mesh_cells`` (4, n_el).
    """
    from skfem import Basis, ElementQuad1, ElementVector, MeshQuad1

    from .io.results import check_mesh

    p, t, uu = check_mesh(mesh_points, mesh_cells, u)
    try:
        basis = Basis(MeshQuad1(p, t), ElementVector(ElementQuad1()), quadrature=ELEMENT_CENTRE_RULE)
    except Exception as exc:  # noqa: BLE001  scikit-fem raises a bare Exception for a zero Jacobian
        raise InputError(f"mesh has degenerate (zero-area) quads ({exc})") from None
    return strain_components(np.asarray(basis.interpolate(uu).grad)[:, :, :, 0])
