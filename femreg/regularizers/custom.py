r"""User-defined regularisers in a few lines (FEniCSx style: write the weak form, get a regulariser).

The built-ins are instances of the same constructions (paper arXiv:2508.19086: R_eps / R_eps_i are route (a),
the momentum regularisers R_P_eps / R_P_sigma route (b)).

Two routes, both returning a :class:`~femreg.regularizers.base.Regularizer` that ``femreg.register(...,
regularizer=...)`` accepts directly (or by name after :func:`~femreg.regularizers.register_regularizer`).

(a) Quadratic regulariser from a scikit-fem ``BilinearForm``: :math:`R[u] = \tfrac{\alpha}{2} a(u, u)`,
    Hessian :math:`\alpha A` exact.  The built-in R_eps is exactly this with
    :math:`a(u, v) = \int \nabla^s u : \nabla^s v` on 3x3 Gauss points::

        from skfem import BilinearForm
        from skfem.helpers import sym_grad
        import femreg
        from femreg.regularizers import from_form

        @BilinearForm
        def lateral_strain(u, v, w):            # penalise only eps_yy (y = lateral)
            return sym_grad(u)[1, 1] * sym_grad(v)[1, 1]

        reg = from_form(lateral_strain, alpha=1e-3, quadrature="gauss3")
        res = femreg.register(ref, mov, spacing=(dx, dy), regularizer=reg)

    Coordinates are available in the form as ``w.x`` (``w.x[0]`` axial, ``w.x[1]`` lateral, mm), so spatially
    varying weights need no extra plumbing.  Several forms with their own quadrature: :func:`from_forms`.

(b) Total-variation-type regulariser of jumps across interior edges, from weak forms:
    :math:`R[u] = \alpha\sum_j l_j \sqrt{\sum_c [\![f_c(u)]\!]_j^2 + \delta}` (eq:dmreg2 with the user's
    quantities in place of the traction [[A[u]]] n), gradient eq:dmreg3, lagged-diffusivity Hessian eq:dmreg4.
    Each :math:`f_c` is a scikit-fem ``LinearForm`` in the test function; data reach it through ``w``::

        from skfem import LinearForm
        from skfem.helpers import sym_grad
        from femreg.regularizers import from_jump_forms

        @LinearForm
        def lateral_strain(v, w):               # eps_yy, scaled by a user parameter
            return w.scale * sym_grad(v)[1, 1]

        reg = from_jump_forms([lateral_strain], alpha=0.1, scale=1.0)

    The built-in momentum regularisers are exactly this with the two components of A[u] n
    (:func:`~femreg.regularizers.momentum.momentum_jump_operators`).

(c) Total-variation-type regulariser from any linear operator: :math:`R[u] = \alpha\sum_j w_j \phi(|K_j u|^2)`.
    The user supplies ``operator(mesh) -> (components, weights)``; :func:`centre_gradient_operators`
    and :func:`~femreg.regularizers.momentum.facet_jump_operators` give the usual building blocks::

        from femreg.regularizers import from_operator, centre_gradient_operators

        def shear_tv(mesh):                     # TV of the shear strain, element by element
            G, area = centre_gradient_operators(mesh)
            return [0.5 * (G["xy"] + G["yx"])], area

        reg = from_operator(shear_tv, alpha=1e-4)
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..fields import _unit_centre_gradients, centre_gradient_operators  # noqa: F401  (part of this API)
from ..quadrature import EDGE_MIDPOINT_RULE, QUADRATURES
from .base import QuadraticFormRegularizer, Regularizer
from .momentum import DEFAULT_DELTA, TVRegularizer, facet_jump_operators


def _resolve_quadrature(quadrature):
    if quadrature is None or isinstance(quadrature, (int, np.integer)):
        return quadrature
    if isinstance(quadrature, str):
        if quadrature not in QUADRATURES:
            raise ValueError(f"unknown quadrature {quadrature!r}; use one of {sorted(QUADRATURES)}, an intorder "
                             "int, or a (points, weights) tuple on [0, 1]^2")
        return QUADRATURES[quadrature]
    if isinstance(quadrature, tuple) and len(quadrature) == 2:
        pts, wts = np.asarray(quadrature[0], float), np.asarray(quadrature[1], float)
        if pts.ndim != 2 or pts.shape[0] != 2 or wts.shape != (pts.shape[1],):
            raise ValueError(f"quadrature (points, weights) must have shapes (2, q) and (q,), got "
                             f"{pts.shape} and {wts.shape}")
        return (pts, wts)
    raise ValueError(f"quadrature must be None, an int, a name in {sorted(QUADRATURES)} or (points, weights); "
                     f"got {quadrature!r}")


def _check_form(form) -> None:
    from skfem import BilinearForm

    if not isinstance(form, BilinearForm):
        raise ValueError(f"expected a skfem.BilinearForm (decorate your function with @BilinearForm), got "
                         f"{type(form).__name__}")


def from_forms(terms: Sequence[tuple], alpha: float = 1.0, *, name: str = "custom-quadratic", **w) -> Regularizer:
    r"""Quadratic regulariser :math:`\tfrac{\alpha}{2}\sum_k c_k\, a_k(u, u)` from several BilinearForms.

    Parameters
    ----------
    terms : sequence of (form, weight, quadrature)
        ``form`` a ``skfem.BilinearForm`` on vector fields (``ElementVector(ElementQuad1())``), ``weight``
        :math:`c_k \ge 0`, ``quadrature`` as in :func:`from_form`.
    alpha : float
        Overall weight :math:`\alpha`.
    name : str
        Label in results.
    **w
        User data for the forms, available there as ``w.<name>`` (numbers as they are; nodal vectors of the
        vector basis interpolated by scikit-fem).
    """
    if not terms:
        raise ValueError("from_forms needs at least one (form, weight, quadrature) term")
    resolved = []
    for t in terms:
        if not (isinstance(t, tuple) and len(t) == 3):
            raise ValueError(f"each term must be (form, weight, quadrature), got {t!r}")
        form, weight, quad = t
        _check_form(form)
        weight = float(weight)
        if not np.isfinite(weight) or weight < 0:
            raise ValueError(f"term weight must be finite and >= 0, got {weight!r}")
        resolved.append((form, weight, _resolve_quadrature(quad)))
    return QuadraticFormRegularizer(resolved, alpha=alpha, name=name, w=w)


def from_form(form, alpha: float = 1.0, *, quadrature="gauss3", name: str = "custom-quadratic",
              **w) -> Regularizer:
    r"""Quadratic regulariser :math:`R[u] = \tfrac{\alpha}{2} a(u, u)` from one scikit-fem ``BilinearForm``.

    Parameters
    ----------
    form : skfem.BilinearForm
        Symmetric positive semi-definite form :math:`a(u, v)` on vector fields, written with ``skfem.helpers``
        (``sym_grad``, ``div``, ``ddot``, ...); coordinates in ``w.x`` (mm).
    alpha : float
        :math:`\alpha` (the form carries its own scale, so there is no generic default).
    quadrature : "gauss3", "gauss2", "centre", int or (points, weights)
        Rule on the reference square [0, 1]^2: named, a scikit-fem ``intorder``, or explicit points (2, q) and
        weights (q,).  "gauss3" (3x3 Gauss) is what R_eps uses.
    name : str
        Label in results.
    **w
        User data for the form (``w.<name>``), as in :func:`from_forms`.

    Returns
    -------
    QuadraticFormRegularizer
        Energy :math:`\tfrac{\alpha}{2}u^T A u`, gradient :math:`\alpha A u`, Hessian :math:`\alpha A`; A is
        assembled once per mesh.
    """
    return from_forms([(form, 1.0, quadrature)], alpha=alpha, name=name, **w)


def from_operator(operator: Callable, alpha: float = 1.0, *, delta: float = DEFAULT_DELTA, penalty="tv",
                  name: str = "custom-tv") -> Regularizer:
    r"""TV-type regulariser :math:`\alpha\sum_j w_j\,\phi(|K_j u|^2)` from a user's linear operator (eq:dmreg2).

    Parameters
    ----------
    operator : callable
        ``operator(mesh) -> (components, weights)``: ``components`` a list of m sparse matrices of shape
        (n_terms, 2 n_nodes), row j of each being one component of term j (e.g. ``[Kx, Ky]`` for a vector jump,
        one matrix for a scalar); ``weights`` (n_terms,) >= 0 (edge lengths, element areas).  Called once per
        mesh.
    alpha : float
        :math:`\alpha`.
    delta : float
        :math:`\delta` > 0 of :math:`\phi(s) = \sqrt{s + \delta}`.
    penalty : "tv", "huber", "quadratic" or (phi, dphi)
        :math:`\phi(s)` and :math:`d\phi/ds \ge 0` as vectorised callables of the squared term norm s.
    name : str
        Label in results.

    Returns
    -------
    TVRegularizer
        Gradient eq:dmreg3, lagged-diffusivity Hessian eq:dmreg4 (symmetric PSD).
    """
    if not callable(operator):
        raise ValueError(f"operator must be a callable mesh -> (components, weights), got {operator!r}")
    return TVRegularizer(operator, alpha, delta=delta, penalty=penalty, name=name)


def from_jump_forms(forms, alpha: float = 1.0, *, delta: float = DEFAULT_DELTA, penalty="tv",
                    quadrature=EDGE_MIDPOINT_RULE, name: str = "custom-jump-tv", **w) -> Regularizer:
    r"""TV regulariser of the jumps of weak-form quantities across interior edges (eq:dmreg2 with user terms).

    :math:`R[u] = \alpha\sum_j l_j\,\phi\big(\sum_c [\![f_c(u)]\!]_j^2\big)`, :math:`\phi(s) = \sqrt{s+\delta}`
    by default, where :math:`[\![f_c(u)]\!]_j` is the mean of :math:`f_c` over edge j on side 0 minus side 1
    (:func:`~femreg.regularizers.momentum.facet_jump_operators`).

    Parameters
    ----------
    forms : skfem.LinearForm or sequence of them
        :math:`f_c(v, w)`, linear in the vector test function v (``ElementVector(ElementQuad1())``), written with
        ``skfem.helpers``; ``w.n`` is the side-0 unit normal, ``w.x`` the coordinates (mm).
    alpha, delta, penalty, name
        As in :func:`from_operator`.
    quadrature : (points, weights)
        Rule on the reference edge [0, 1]; default the midpoint (as the momentum regularisers, eq:Ae7).
    **w
        User data passed to the forms as ``w.<name>`` (numbers as they are; nodal vectors of the vector basis
        are interpolated by scikit-fem).

    Returns
    -------
    TVRegularizer
    """
    from skfem import LinearForm

    forms = [forms] if isinstance(forms, LinearForm) else list(forms)
    if not forms or not all(isinstance(f, LinearForm) for f in forms):
        raise ValueError("from_jump_forms needs skfem.LinearForm(s) (decorate your function with @LinearForm)")

    def operator(mesh):
        comps, lengths, _ = facet_jump_operators(mesh, forms, quadrature=quadrature, **w)
        return comps, lengths

    return TVRegularizer(operator, alpha, delta=delta, penalty=penalty, name=name)


