"""Quadrature rules used by femreg's weak forms (one home for each rule).

Rules on the reference cell of scikit-fem: the square [0, 1]^2 for quads, the segment [0, 1] for their edges.
A rule is a scikit-fem ``intorder`` int or a ``(points, weights)`` pair.  The image term is integrated at pixel
centres instead (paper appendix "Numerical Integration"; :mod:`femreg.pixels`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["GAUSS_3X3", "GAUSS_2X2", "ELEMENT_CENTRE_RULE", "EDGE_MIDPOINT_RULE", "QUADRATURES"]

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

#: Named rules for user forms (:func:`femreg.regularizers.from_form`).
QUADRATURES = {"gauss3": GAUSS_3X3, "gauss2": GAUSS_2X2, "centre": ELEMENT_CENTRE_RULE,
               "center": ELEMENT_CENTRE_RULE}
