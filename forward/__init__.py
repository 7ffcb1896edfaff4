"""forward: finite-element ground truth (2D plane strain / plane stress, 3D) and ultrasound RF simulation.

Ground truth (issue 2): :func:`solve_elasticity` -> :class:`Solution` with ``displacement(points)`` /
``strain(points)`` in the imaging plane; :func:`cached_solve` (disk cache), :func:`load_solution`.
"""
from .elasticity import (MODELS, Solution, cache_dir, cached_solve, elasticity_form, lame_parameters,
                         load_solution, solve_elasticity)

__all__ = ["MODELS", "Solution", "cache_dir", "cached_solve", "elasticity_form", "lame_parameters",
           "load_solution", "solve_elasticity"]
