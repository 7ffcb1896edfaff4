"""What every registration result holds, 2D (:class:`femreg.result.RegistrationResult`) and 3D
(:class:`femreg.volume_result.VolumeResult`): the mesh, the nodal displacement and the run's record."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ResultRecord", "RefinementRecord"]


class ResultRecord:
    """Base of the result classes: :meth:`_record` stores the fields both dimensions share, typed.

    ``u``: nodal displacement, interleaved per node (2 or 3 values), mm; ``shape``: the reference's samples;
    ``spacing``, ``origin``: mm; ``quality``: one value per element (local NCC) or None."""

    def _record(self, mesh, u, *, shape, spacing, origin, regularizer, alpha, success, status, message, nit,
                energy_history, ncc_before, ncc_after, timings, quality, strategy, alpha_effective,
                solver_result) -> None:
        self.mesh = mesh
        self.u = np.asarray(u, float)
        self.shape = tuple(int(s) for s in shape)
        self.spacing = np.asarray(spacing, float)
        self.origin = np.asarray(origin, float)
        self.regularizer = str(regularizer)
        self.alpha = float(alpha)
        self.success = bool(success)
        self.status = int(status)
        self.message = str(message)
        self.nit = int(nit)
        self.energy_history = np.asarray(energy_history, float)
        self.ncc_before = float(ncc_before)
        self.ncc_after = float(ncc_after)
        self.timings = dict(timings or {})
        self.quality = None if quality is None else np.asarray(quality, float)
        self.strategy = str(strategy)
        self.alpha_effective = float(alpha_effective)
        self.solver_result = solver_result


@dataclass
class RefinementRecord:
    """What each pass did: elements before, rows and columns split, Gauss-Newton iterations, seconds; and
    ``base_size``, the median element size (axial, lateral) mm of the mesh refinement started from (what a
    caller sizing a new mesh from the result's should read: the refined mesh's median is smaller).  ``passes``
    is None for a result read from a file (:func:`femreg.load_result` keeps ``base_size`` only)."""

    passes: list
    base_size: tuple | None = None

    def summary(self) -> str:
        if self.passes is None:         # read back from a result file, which keeps the starting size only
            return f"refinement: refined from {' x '.join(f'{v:.3g}' for v in self.base_size)} mm elements"
        if not self.passes:
            return "refinement: nothing marked"
        parts = [f"{p['elements']} -> {p['elements_after']} elements ({p['rows']} rows, {p['columns']} columns split"
                 + (f", {p['relaxed_edges']} edges relaxed" if p.get("relaxed_edges") else "") + ")"
                 for p in self.passes]
        return "refinement: " + "; ".join(parts)
