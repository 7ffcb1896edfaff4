"""Quadrature rules used by femreg's weak forms (one home for each rule).

Rules on the reference cell of scikit-fem: the square [0, 1]^2 for quads, the segment [0, 1] for their edges.
A rule is a scikit-fem ``intorder`` int or a ``(points, weights)`` pair.  The image term is integrated at pixel
centres instead (paper appendix "Numerical Integration"; :mod:`femreg.pixels`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["GAUSS_3X3", "GAUSS_2X2", "ELEMENT_CENTRE_RULE", "EDGE_MIDPOINT_RULE", "QUADRATURES",
           "ELEMENT_CENTRE_RULE_3D", "FACE_CENTRE_RULE", "for_dimension"]

#: 3x3 Gauss rule on quads (scikit-fem's intorder 4 and 5 both give it): R_eps (paper appendix "Numerical
#: Integration") and the error metrics.
GAUSS_3X3 = 5
#: 2x2 Gauss rule on quads.
GAUSS_2X2 = 2
#: 1-point element-centre rule on [0, 1]^2: reduced integration of the dilatation (R_eps_i, R_P_eps), element
#: strains.
ELEMENT_CENTRE_RULE = (np.array([[0.5], [0.5]]), np.array([1.0]))
#: 1-point midpoint rule on the reference edge [0, 1]: the traction jumps of eq:Ae7 / eq:dmreg2.
EDGE_MIDPOINT_RULE = (np.array([[0.5]]), np.array([1.0]))

#: 1-point centre rule on the reference cube [0, 1]^3 (hexahedra): the 3D form of :data:`ELEMENT_CENTRE_RULE`.
ELEMENT_CENTRE_RULE_3D = (np.array([[0.5], [0.5], [0.5]]), np.array([1.0]))
#: 1-point centre rule on the reference square face [0, 1]^2 of a hexahedron: the traction jumps in 3D.
FACE_CENTRE_RULE = (np.array([[0.5], [0.5]]), np.array([1.0]))


def for_dimension(rule, dim: int):
    """``rule`` for cells of dimension ``dim``: the element-centre rule of the square is the cube's centre on
    hexahedra and the edge midpoint rule is the face centre (the same 1-point rules one dimension up); integer
    orders and other rules pass through."""
    if dim == 3 and isinstance(rule, tuple):
        pts = np.asarray(rule[0])
        if pts.shape == (2, 1) and np.all(pts == 0.5):
            return ELEMENT_CENTRE_RULE_3D
        if pts.shape == (1, 1) and np.all(pts == 0.5):
            return FACE_CENTRE_RULE
    return rule


#: Named rules for user forms (:func:`femreg.regularizers.from_form`).
QUADRATURES = {"gauss3": GAUSS_3X3, "gauss2": GAUSS_2X2, "centre": ELEMENT_CENTRE_RULE,
               "center": ELEMENT_CENTRE_RULE}
