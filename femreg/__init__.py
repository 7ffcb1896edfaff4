"""femreg: finite-element variational image registration for quasi-static ultrasound elastography,
regularised by the momentum equation of a nearly incompressible solid (SPREME).

Public entry points (filled in by their modules): :func:`register` (-> :class:`RegistrationResult`,
saved/loaded with ``res.save`` / :func:`load_result`), :func:`track`, :func:`invert` (shear-modulus images -> :class:`InversionResult`),
:mod:`femreg.regularizers`, :mod:`femreg.metrics`, :mod:`femreg.io`.
"""
__version__ = "0.1.0"

from .errors import FileFormatError, InputError  # noqa: F401
from .registration import RegistrationResult, load_result, register  # noqa: E402,F401
from .sequence import SequenceResult, load_track, track  # noqa: E402,F401
from .inversion import InversionResult, invert, load_inversion  # noqa: E402,F401

from .geometry import Convex, Sector, Swept  # noqa: E402,F401
from .volume_result import SweptResult, VolumeResult, load_volume_result  # noqa: E402,F401
from . import metrics, regularizers  # noqa: E402,F401

__all__ = ["register", "Convex", "Sector", "Swept", "RegistrationResult", "load_result", "VolumeResult", "SweptResult", "load_volume_result", "track", "SequenceResult", "load_track", "metrics",
           "regularizers", "InputError", "FileFormatError", "__version__", "invert", "InversionResult",
           "load_inversion"]
