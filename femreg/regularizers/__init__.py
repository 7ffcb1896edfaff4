"""Regularisers R[u] of eq:objf.  See :mod:`femreg.regularizers.base` for the interface."""
from .base import (QuadraticFormRegularizer, Regularizer, available_regularizers, make_regularizer,
                   register_regularizer)

__all__ = ["Regularizer", "QuadraticFormRegularizer", "register_regularizer", "make_regularizer",
           "available_regularizers"]

# Built-ins register themselves on import (one line per module; keep this list sorted).
from . import strain  # noqa: E402,F401  R_eps, R_eps_i  (issue: registration engine)
