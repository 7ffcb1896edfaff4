"""forward: finite-element ground truth (2D plane strain / plane stress, 3D) and ultrasound RF simulation."""

# RF ultrasound simulation and the paper's image sequences (issue 3).
from . import ultrasound  # noqa: E402,F401
from .sequences import (  # noqa: E402,F401
    INCLUSIONS, PAPER_DATASETS, AnalyticField, Sequence, get_sequence, load_sequence, paper_datasets,
    paper_schedule, schedule_figures, simulate_sequence,
)
from .ultrasound import PSF, ImagingGrid, bmode, envelope  # noqa: E402,F401
