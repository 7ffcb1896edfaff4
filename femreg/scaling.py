"""How the regularisation weight alpha is made independent of the mesh: the ONE place where it is scaled.

The objective is eq:objf, ``pi = psi + alpha_eff R``.  Both terms are integrals over the region in mm^2 already:
psi sums pixel residuals with weights ``dx dy`` (eq:IR by the pixel midpoint rule, :mod:`femreg.data_term`), so
it does not change with the pixel spacing; the strain regularisers are area integrals and the momentum ones
(eq:dmreg2, a sum of edge jumps times edge lengths) approximate the area integral of ``|div A|``.  What does change
with the mesh is the noise the data term leaves in each element: an element of area A holds A / (dx dy)
pixels, its nodal displacements are fixed by fewer samples as A shrinks, and the regularisation needed to hold
the same image quality grows like 1 / A.  Measured with the paper's procedure (docs/study_report.md, 3d-HI
frames 1 -> 7, best alpha at element sizes 1 / 2 / 3 mm): R_P_sigma 0.4 / 0.133 / 0.04, R_eps 53 / 17.8 / 17.8,
i.e. about 3x per halving of the element size (1 / A predicts 4x).

So the user's alpha is the weight for elements of :data:`REFERENCE_ELEMENT_AREA` (2 x 2 mm, the paper-protocol
mesh), and the weight used in the objective is

    alpha_eff = alpha * REFERENCE_ELEMENT_AREA / (mean element area of the mesh).

On the paper's image (72 x 44 mm, dx 0.0192 mm, dy 0.3 mm) the default 2 mm mesh rounds its elements to whole
pixels (mean area 3.96-3.97 mm^2), so alpha_eff = 1.008-1.010 alpha there: the alphas selected by the paper's
procedure (femreg/data/default_alphas.json) keep their meaning within 1 %.
"""
from __future__ import annotations

import numpy as np

__all__ = ["REFERENCE_ELEMENT_AREA", "REFERENCE_ELEMENT_VOLUME", "mean_element_area", "mean_element_volume",
           "alpha_scale", "effective_alpha", "refined_alpha"]

#: Element area (mm^2) at which the user's alpha is the weight of eq:objf as written: 2 mm x 2 mm.
REFERENCE_ELEMENT_AREA = 4.0


#: Element volume (mm^3) at which the user's alpha is the weight of eq:objf on a volume (hexahedral mesh):
#: 2 x 2 x 2 mm.  On volumes psi and R are integrals over mm^3 (voxel weights dx dy dz); an element of volume V
#: holds V / (dx dy dz) voxels, so the same argument gives alpha_eff = alpha * REFERENCE_ELEMENT_VOLUME / V.
#: A volume that is constant along z registers with the same in-plane weight as its 2D plane on 2 mm elements
#: (psi and R both scale with the thickness).
REFERENCE_ELEMENT_VOLUME = 8.0


def mean_element_volume(mesh) -> float:
    """Mean volume (mm^3) of the hexahedra of ``mesh`` (scikit-fem's 2 x 2 x 2 Gauss rule, exact for trilinear
    maps)."""
    from skfem import Basis, ElementHex1

    return float(np.mean(Basis(mesh, ElementHex1(), intorder=2).dx.sum(axis=1)))


def mean_element_area(mesh) -> float:
    """Mean area (mm^2) of the quadrilaterals of ``mesh`` (shoelace formula over the 4 corners)."""
    p = np.asarray(mesh.p, float)[:, np.asarray(mesh.t)]          # (2, 4, n_el)
    x, y = p[0], p[1]
    a = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=0) - np.roll(x, -1, axis=0) * y, axis=0))
    return float(np.mean(a))


def alpha_scale(mesh) -> float:
    """Factor from the user's alpha to the weight used in eq:objf on ``mesh`` (module docstring)."""
    if np.asarray(mesh.p).shape[0] == 3:
        vol = mean_element_volume(mesh)
        if not vol > 0:
            raise ValueError("mesh has elements of zero volume")
        return REFERENCE_ELEMENT_VOLUME / vol
    area = mean_element_area(mesh)
    if not area > 0:
        raise ValueError("mesh has elements of zero area")
    return REFERENCE_ELEMENT_AREA / area


def effective_alpha(alpha: float, mesh) -> float:
    """``alpha * alpha_scale(mesh)``."""
    return float(alpha) * alpha_scale(mesh)


def refined_alpha(alpha: float, base_mesh, mesh) -> float:
    """The alpha to give a solve on ``mesh``, a refinement of ``base_mesh`` (:mod:`femreg.refine`), so that its
    weight in eq:objf is the base mesh's: ``effective_alpha(refined_alpha(a, base, mesh), mesh) ==
    effective_alpha(a, base)``.  A strain step then costs the same total variation on both meshes.  Quadrilaterals
    or hexahedra (the ratio of mean element areas or volumes)."""
    return float(alpha) * alpha_scale(base_mesh) / alpha_scale(mesh)
