"""What a scanner exports instead of RF: log-compressed 8-bit B-mode, and the fan of a scan-converted sector
(the fixed wedges of fill around a convex / phased probe's image)."""
from __future__ import annotations

import numpy as np

__all__ = ["bmode_uint8", "sector_fan"]


def bmode_uint8(rf, dynamic_range_db: float = 50.0, *, axis: int = 0, floor: float = 1e-6) -> np.ndarray:
    """8-bit display B-mode of RF data: the envelope (analytic signal along ``axis``, the axial one), dB re the
    largest envelope of the whole array (a loop keeps one gain), the top ``dynamic_range_db`` dB mapped to 0-255.
    Same shape as ``rf``, uint8."""
    from scipy.signal import hilbert

    env = np.abs(hilbert(np.asarray(rf, float), axis=axis))
    db = 20.0 * np.log10(env / env.max() + floor)
    return np.clip((db + dynamic_range_db) / dynamic_range_db * 255.0, 0, 255).astype(np.uint8)


def sector_fan(shape, spacing, origin=(0.0, 0.0), apex_mm: float = 20.0, top_half_width_mm: float = 4.0) -> np.ndarray:
    """True inside a sector's fan, (n_axial, n_lateral) bool: rays from an apex ``apex_mm`` above the first row,
    on the image's lateral centre, whose half-width at the first row is ``top_half_width_mm``.  ``shape`` (2,),
    ``spacing`` (2,) mm, ``origin`` (2,) mm."""
    x = origin[0] + spacing[0] * np.arange(shape[0])
    y = origin[1] + spacing[1] * np.arange(shape[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    half = np.arctan2(top_half_width_mm, apex_mm)
    return np.abs(np.arctan2(Y - np.mean(y), X - (x[0] - apex_mm))) <= half
