"""The paper's simulation study (arXiv 2508.19086, "Results" and appendix "Algorithmic Parameter Justification"):
alpha selection, single-frame, dual-frame and accumulated registrations of the six simulated data sets, a report
with every femreg number beside the paper's.  A separate package because it needs both the registration library
(:mod:`femreg`) and the simulator (:mod:`forward`), while femreg must not depend on forward.  It adds the
``femreg study`` subcommand through the ``femreg.commands`` entry-point group (see :mod:`paperstudy.cli`)."""
from .study import (LABELS, PAPER, PAPER_ALPHAS, PAPER_TRUE, REGULARIZERS, StudyResult, StudySettings,
                    case_metrics, read_default_alphas, run_study, select_alphas, write_default_alphas, write_report)

__all__ = ["StudySettings", "StudyResult", "run_study", "select_alphas", "case_metrics", "write_report",
           "read_default_alphas", "write_default_alphas", "PAPER", "PAPER_ALPHAS", "PAPER_TRUE", "REGULARIZERS",
           "LABELS"]
