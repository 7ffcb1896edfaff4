"""forward: finite-element ground truth (2D plane strain / plane stress, 3D) and ultrasound RF simulation.

Ground truth (issue 2): :func:`solve_elasticity` -> :class:`Solution` with ``displacement(points)`` /
``strain(points)`` in the imaging plane; :func:`cached_solve` (disk cache), :func:`load_solution`.
RF simulation (issue 3): :func:`simulate_sequence` -> :class:`Sequence`; :func:`load_sequence`,
:func:`get_sequence` / :func:`paper_datasets` (cached data sets of the paper).
"""
from .elasticity import (MODELS, Solution, cache_dir, cached_solve, elasticity_form, lame_parameters,
                         load_solution, solve_elasticity)
from . import ultrasound  # noqa: E402,F401
from .sequences import (  # noqa: E402,F401
    INCLUSIONS, PAPER_DATASETS, AnalyticField, Sequence, get_sequence, load_sequence, paper_datasets,
    paper_schedule, schedule_figures, simulate_sequence,
)
from .ultrasound import PSF, ImagingGrid, bmode, envelope  # noqa: E402,F401

__all__ = ["MODELS", "Solution", "cache_dir", "cached_solve", "elasticity_form", "lame_parameters",
           "load_solution", "solve_elasticity", "INCLUSIONS", "PAPER_DATASETS", "AnalyticField", "Sequence",
           "get_sequence", "load_sequence", "paper_datasets", "paper_schedule", "schedule_figures",
           "simulate_sequence", "PSF", "ImagingGrid", "bmode", "envelope"]
