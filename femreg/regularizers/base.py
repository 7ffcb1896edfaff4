"""The regulariser interface: one term R[u] of the objective pi = psi + R (paper eq:objf).

Every regulariser, built-in or user-written, implements :class:`Regularizer`:

* ``setup(mesh)`` is called once per mesh; build operators here (never per iteration).
* ``energy(u)``, ``gradient(u)``, ``hessian(u)`` at a nodal displacement ``u``.

``u`` is the nodal vector of a scikit-fem ``ElementVector(ElementQuad1())`` basis on that mesh, shape
``(2 * n_nodes,)`` (on a hexahedral ``MeshHex1`` of a volume: ``ElementVector(ElementHex1())``, ``(3 * n_nodes,)``), in millimetres, in scikit-fem's DOF order (any Basis built with that element on the same
mesh numbers DOFs identically).  ``hessian`` returns a symmetric positive semi-definite sparse matrix
(exact for quadratic terms, lagged diffusivity for total-variation terms, eq:dmreg4).
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp


class Regularizer:
    """Base class for R[u].  Subclasses set ``name`` and ``default_alpha`` and implement the four methods.

    Parameters
    ----------
    alpha : float or None
        Weight :math:`\\alpha` of the term in eq:objf (for femreg's image normalisation, see
        ``femreg.image``).  ``None`` takes ``default_alpha``.
    """

    name: str = "base"
    default_alpha: float = 1.0
    #: True when energy is exactly 1/2 u^T H u (the engine may then reuse H across iterations).
    quadratic: bool = False

    def __init__(self, alpha: float | None = None):
        alpha = self.default_alpha if alpha is None else alpha
        alpha = float(alpha)
        if not np.isfinite(alpha) or alpha < 0:
            raise ValueError(f"alpha must be a finite number >= 0, got {alpha!r}")
        self.alpha = alpha
        self.mesh = None

    def setup(self, mesh) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def energy(self, u: np.ndarray) -> float:  # pragma: no cover - interface
        raise NotImplementedError

    def gradient(self, u: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def hessian(self, u: np.ndarray) -> sp.spmatrix:  # pragma: no cover - interface
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, alpha={self.alpha:g})"


class QuadraticFormRegularizer(Regularizer):
    """R[u] = alpha/2 * u^T K u with K assembled from scikit-fem BilinearForms (FEniCSx style).

    Parameters
    ----------
    terms : sequence of (form, weight, quadrature)
        ``form`` a ``skfem.BilinearForm`` on vector fields; ``weight`` multiplies it (relative to alpha);
        ``quadrature`` is an ``intorder`` int, or a ``(points, weights)`` tuple on the reference square
        [0, 1]^2 (e.g. the 1-point centre rule), or None for scikit-fem's default.
    alpha : float
        Overall weight.
    name : str
        Label used in results and reports.
    w : dict, optional
        User data for the forms, available there as ``w.<name>`` (scikit-fem's assembly keywords).
    """

    quadratic = True

    def __init__(self, terms: Sequence[tuple], alpha: float | None = None, name: str = "custom-quadratic",
                 w: dict | None = None):
        super().__init__(alpha)
        if not terms:
            raise ValueError("QuadraticFormRegularizer needs at least one (form, weight, quadrature) term")
        self.terms = list(terms)
        self.name = name
        self.w = dict(w or {})
        self._K = None

    def setup(self, mesh) -> None:
        from skfem import Basis, ElementVector

        from ..quadrature import for_dimension

        K = None
        for form, weight, quad in self.terms:
            kw = {}
            if isinstance(quad, (int, np.integer)):
                kw["intorder"] = int(quad)
            elif quad is not None:
                kw["quadrature"] = for_dimension(quad, mesh.p.shape[0])
            basis = Basis(mesh, ElementVector(nodal_element(mesh)), **kw)
            Ki = float(weight) * form.assemble(basis, **self.w)
            K = Ki if K is None else K + Ki
        self._K = sp.csr_matrix(K)
        self.mesh = mesh

    @property
    def matrix(self) -> sp.csr_matrix:
        """Unscaled stiffness K (alpha excluded)."""
        if self._K is None:
            raise RuntimeError("call setup(mesh) first")
        return self._K

    def energy(self, u):
        return 0.5 * self.alpha * float(u @ (self.matrix @ u))

    def gradient(self, u):
        return self.alpha * (self.matrix @ u)

    def hessian(self, u=None):
        return self.alpha * self.matrix


def nodal_element(mesh):
    """The scalar element of femreg's displacement on ``mesh``: bilinear quads (``ElementQuad1``) in 2D,
    trilinear hexahedra (``ElementHex1``) in 3D; the vector field is ``ElementVector`` of it in either."""
    from skfem import ElementHex1, ElementQuad1, MeshHex1

    return ElementHex1() if isinstance(mesh, MeshHex1) else ElementQuad1()


_REGISTRY: dict[str, Callable[..., Regularizer]] = {}


def register_regularizer(name: str, factory: Callable[..., Regularizer]) -> None:
    """Make ``factory(alpha=..., **kw)`` available as ``regularizer=name`` in register/track/CLI."""
    _REGISTRY[name] = factory


def available_regularizers() -> list[str]:
    return sorted(_REGISTRY)


def make_regularizer(spec, alpha: float | None = None, **kwargs) -> Regularizer:
    """Resolve a name (see :func:`available_regularizers`) or pass a Regularizer instance through.

    An instance is returned as it is when ``alpha`` is None, otherwise as a (shallow) copy carrying ``alpha``: the
    caller's instance keeps its own weight."""
    if isinstance(spec, Regularizer):
        if alpha is not None:
            import copy

            spec = copy.copy(spec)
            spec.alpha = float(alpha)
        return spec
    if not isinstance(spec, str) or spec not in _REGISTRY:
        raise ValueError(f"unknown regularizer {spec!r}; choose one of {available_regularizers()} "
                         "or pass a femreg.regularizers.Regularizer instance")
    return _REGISTRY[spec](alpha=alpha, **kwargs)
