"""What every registration result holds, 2D (:class:`femreg.result.RegistrationResult`) and 3D
(:class:`femreg.volume_result.VolumeResult`): the mesh, the nodal displacement and the run's record."""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from .errors import FileFormatError, counted

__all__ = ["ResultRecord", "RefinementRecord", "AutoAlpha", "read_auto_alpha", "FRESH_NOTE"]

#: The words of the note a result started afresh by :func:`femreg.initial.previous_or_fresh` carries in its
#: message (:attr:`ResultRecord.started_afresh` is the flag; files of earlier versions have the note only).
FRESH_NOTE = "started afresh"


class ResultRecord:
    """Base of the result classes: :meth:`_record` stores the fields both dimensions share, typed.

    ``u``: nodal displacement, interleaved per node (2 or 3 values), mm; ``shape``: the reference's samples;
    ``spacing``, ``origin``: mm; ``quality``: one value per element (local NCC) or None; ``auto_alpha``: the
    :class:`AutoAlpha` record of ``alpha="auto"`` (None otherwise); ``started_afresh``: True where a track's
    increment was registered from the strategy's own start instead of the previous increment
    (:func:`femreg.initial.previous_or_fresh`; a volume's increment never is)."""

    auto_alpha = None
    started_afresh = False

    def _auto_alpha_record(self) -> dict:
        """The ``auto_alpha`` entry of a saved result (JSON text of :meth:`femreg.autoalpha.AutoAlpha.as_dict`;
        none without ``alpha="auto"``)."""
        return {} if self.auto_alpha is None else {"auto_alpha": np.array(self.auto_alpha.to_json())}

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


def read_auto_alpha(text, path):
    """The :class:`AutoAlpha` of a saved result's ``auto_alpha`` entry; a :class:`femreg.errors.FileFormatError`
    naming ``path`` when it is not such a record."""
    try:
        return AutoAlpha.from_json(str(np.asarray(text)))
    except FileFormatError as exc:
        raise FileFormatError(f"{path}: {exc}") from None


@dataclass
class AutoAlpha:
    """The choice of ``alpha="auto"`` (:func:`femreg.autoalpha.choose_alpha`) and its curve (arrays over the
    candidate grid, in grid order); a result's ``auto_alpha``, saved with it.

    alpha : chosen alpha (the user-level alpha of :func:`femreg.register`)
    alphas, psi, dof, upre : candidates, image term psi (mm^2), trace T, U(alpha)
    c, sigma2 : the correlation factor and the weighted residual variance of the rule
    n_registrations : registrations run (the grid size); result : the registration at ``alpha``
    """

    alpha: float
    alphas: np.ndarray
    psi: np.ndarray
    dof: np.ndarray
    upre: np.ndarray
    c: float
    sigma2: float
    n_registrations: int
    result: object = field(repr=False, default=None)
    rule: str = "quasi-optimality"
    results: list | None = field(repr=False, default=None)
    #: ||e(alpha_{k+1}) - e(alpha_k)|| of the recovered nodal strains, k = 0 .. len(alphas) - 2
    strain_change: np.ndarray | None = None
    #: candidates whose registration succeeded (0: none did, ``alpha`` is the grid centre's and no choice)
    n_successful: int | None = None

    @classmethod
    def from_dict(cls, d: dict) -> "AutoAlpha":
        """The record :meth:`as_dict` wrote (without the registrations)."""
        arr = {k: np.asarray(d[k], float) for k in ("alphas", "psi", "dof", "upre")}
        ch = d.get("strain_change")
        n_ok = d.get("n_successful")
        return cls(alpha=float(d["alpha"]), c=float(d["c"]), sigma2=float(d["sigma2"]),
                   n_registrations=int(d["n_registrations"]), rule=str(d.get("rule", "quasi-optimality")),
                   strain_change=None if ch is None else np.asarray(ch, float),
                   n_successful=None if n_ok is None else int(n_ok), **arr)

    def to_json(self) -> str:
        """:meth:`as_dict` as JSON text: the ``auto_alpha`` entry of a saved result (2D and volumes)."""
        return json.dumps(self.as_dict())

    @classmethod
    def from_json(cls, text) -> "AutoAlpha":
        """Read :meth:`to_json`'s text; :class:`femreg.errors.FileFormatError` when it is not such a record."""
        try:
            return cls.from_dict(json.loads(str(text)))
        except (ValueError, KeyError, TypeError) as exc:
            raise FileFormatError(f"'auto_alpha' is not a record of femreg.autoalpha ({exc})") from None

    def as_dict(self) -> dict:
        return {"alpha": self.alpha, "alphas": self.alphas.tolist(), "psi": self.psi.tolist(),
                "dof": self.dof.tolist(), "upre": self.upre.tolist(), "c": self.c, "sigma2": self.sigma2,
                "n_registrations": self.n_registrations, "rule": self.rule,
                "strain_change": None if self.strain_change is None else self.strain_change.tolist(),
                "n_successful": self.n_successful}


@dataclass
class RefinementRecord:
    """What each pass did: elements before, rows and columns split, Gauss-Newton iterations, seconds (2D passes:
    also ``top``, the largest row / column jump over the feature test's cut, :attr:`femreg.refine.Refinement.feature`);
    and
    ``base_size``, the median element size (axial, lateral[, elevational]) mm of the mesh refinement started from (what a
    caller sizing a new mesh from the result's should read: the refined mesh's median is smaller); ``slides``, the
    lateral positions (mm) of the slips along the beam found (:func:`femreg.refine.beam_slip_lines`), which a
    bonded elastic model does not describe (:func:`femreg.invert` flags them).  ``passes`` is None for a result
    read from a file (:func:`femreg.load_result` keeps ``base_size`` and ``slides``)."""

    passes: list
    base_size: tuple | None = None
    note: str | None = None         # why nothing was split although something was marked
    slides: tuple = ()              # lateral positions (mm) where tissue slides along the beam

    def summary(self) -> str:
        if self.passes is None:         # read back from a result file: the starting size and the slips only
            text = ("refinement: refined from " + " x ".join(f"{v:.3g}" for v in self.base_size) + " mm elements"
                    if self.base_size is not None else "refinement: read from a file")
            if self.slides:
                text += ("; tissue slides along the beam near y = " + ", ".join(f"{v:.1f}" for v in self.slides)
                         + " mm")
            return text
        if not self.passes:
            return f"refinement: {self.note}" if self.note else "refinement: nothing marked"
        parts = [f"{p['elements']} -> {p['elements_after']} elements ("
                 + (f"{p['rows']} x-, {p['columns']} y-, {p['slices']} z-slabs split" if "slices" in p else
                    f"{counted(p['rows'], 'row')}, {counted(p['columns'], 'column')} split")
                 + (", finer marking" if p.get("fine") else "")
                 + (f", {p['relaxed_edges']} edges relaxed" if p.get("relaxed_edges") else "")
                 + (f", {p['layer_lines']} layer interface lines solved sharp" if p.get("layer_lines") else "") + ")"
                 for p in self.passes]
        return "refinement: " + "; ".join(parts) + (f"; {self.note}" if self.note else "")
