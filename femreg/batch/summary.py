"""The summary of :func:`femreg.batch.run_batch`: one record per task, written as ``summary.csv`` and
``summary.md``.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

from ..errors import counted


__all__ = ["BatchSummary"]


_COLUMNS = ("key", "status", "computed", "task", "n_frames", "ncc_before", "ncc_after", "nit", "success", "flag",
            "wall_s", "cpu_s", "peak_rss_mb", "worker", "output", "input", "error")


@dataclass
class BatchSummary:
    """The outcome of :func:`run_batch`: one record per task (sorted by key), and where the tables are.

    ``records[i]`` keys: key (``name/pair_III-JJJ`` or ``name/track``), status ("ok" | "failed"), computed
    (False: kept from an earlier run), ncc_before/ncc_after/nit/success/flag (registration quality), wall_s,
    cpu_s (CPU time of the worker process during the task), peak_rss_mb (peak resident memory of the worker process during the task, MiB), worker ("host:pid"),
    output (relative to ``out_dir``), input, error.
    """

    out_dir: Path
    records: list
    wall_s: float
    workers: str
    csv_path: Path | None = None
    md_path: Path | None = None

    @property
    def failed(self) -> list:
        return [r for r in self.records if r.get("status") != "ok"]

    @property
    def n_computed(self) -> int:
        return sum(1 for r in self.records if r.get("computed"))

    @property
    def ok(self) -> bool:
        return not self.failed

    def worker_memory(self) -> dict:
        """{worker: (tasks run, peak RSS MiB)} over the tasks computed in this run."""
        out: dict = {}
        for r in self.records:
            if r.get("computed") and r.get("worker"):
                n, m = out.get(r["worker"], (0, 0.0))
                out[r["worker"]] = (n + 1, max(m, r.get("peak_rss_mb") or 0.0))
        return out

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(_COLUMNS)
        for r in self.records:
            w.writerow([_cell(r.get(c), c) for c in _COLUMNS])
        return buf.getvalue()

    def to_markdown(self) -> str:
        cols = [c for c in _COLUMNS if c not in ("input", "worker")]
        lines = [f"# femreg batch: {counted(len(self.records), 'task')}, {len(self.failed)} failed, "
                 f"{self.n_computed} computed in this run",
                 "", f"Workers: {self.workers}; wall time {self.wall_s:.1f} s.", "",
                 "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in self.records:
            lines.append("| " + " | ".join(_cell(r.get(c), c).replace("|", "/") for c in cols) + " |")
        mem = self.worker_memory()
        if mem:
            lines += ["", "| worker | tasks | peak RSS (MiB) |", "|---|---|---|"]
            lines += [f"| {w} | {n} | {m:.0f} |" for w, (n, m) in sorted(mem.items())]
        return "\n".join(lines) + "\n"

    def __repr__(self) -> str:
        return (f"BatchSummary({counted(len(self.records), 'task')}, {len(self.failed)} failed, "
                f"{self.n_computed} computed, "
                f"{self.wall_s:.1f} s, {self.out_dir})")


def _cell(v, col) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4f}" if col.startswith("ncc") else f"{v:.2f}" if col.endswith("_s") else f"{v:.4g}"
    return " ".join(str(v).split())
