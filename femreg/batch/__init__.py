"""Batches on Dask: many recordings registered or tracked in parallel, on this machine or on a cluster.

Two layers, one engine:

* :func:`run_tasks` runs independent tasks (a module-level function and its arguments each) on a Dask
  ``distributed`` cluster: a :class:`~distributed.LocalCluster` of ``workers`` processes with one thread each
  (default), an existing scheduler by address, or a :class:`~distributed.Client` the caller already holds;
  ``workers=0`` runs them one after the other in this process without Dask.  A task that raises, or whose worker
  dies too often (Dask's ``KilledWorker``), becomes a :class:`TaskOutcome` with the error; the others go on.
  The study (alpha sweeps and cases) runs on this engine too.
* :func:`run_batch` registers or tracks recordings (:class:`Job`, one per file or folder of frame files; one task
  per recording, or per frame pair with ``task="register"``).  Each task reads its input by path and writes its
  result atomically into ``OUT/<name>/`` on the worker, then its record (``*.record.json``) last; only the small
  record travels back to the client.  ``OUT/batch.json`` (the manifest) holds every job's settings;
  ``resume=True`` keeps finished tasks and refuses changed settings, as ``femreg track --resume`` does.
  ``OUT/summary.csv`` and ``OUT/summary.md`` list every task at the end.

Output names are deterministic (the recording's file or folder name; ``pair_III-JJJ.npz`` per registered pair;
``frame_KKK.npz`` + ``track.json`` per tracked recording, the folder layout of ``femreg track``).

Worker processes get one BLAS thread each (Dask's nanny sets ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` /
``MKL_NUM_THREADS`` to 1 before a worker starts: ``distributed.nanny.pre-spawn-environ``), so N workers use N
cores.  Every record carries the task's wall time and the peak resident memory of its worker process during the
task (Linux: ``VmHWM`` after resetting it through ``/proc/self/clear_refs``).

A worker that dies (killed, out of memory, node lost) loses no finished result: results are on disk before the
task ends, Dask reschedules the tasks the worker held, and a rescheduled task whose record is already written
returns it without recomputing; a track that was cut short continues from its last checkpointed frame.

Local scripts that call :func:`run_batch` / :func:`run_tasks` with a LocalCluster must guard their main code with
``if __name__ == "__main__":`` (Dask starts workers by *spawn*, which imports the calling script).

Modules, one job each: :mod:`~femreg.batch.engine` (tasks on Dask), :mod:`~femreg.batch.settings` (the settings
schema, shared with the command line through :mod:`femreg.options`), :mod:`~femreg.batch.inputs` (recordings
and their settings files), :mod:`~femreg.batch.running` (the task of one recording, :func:`run_batch`),
:mod:`~femreg.batch.summary` (the tables).
"""
from .engine import WORKER_ENV, Task, TaskOutcome, open_client, run_tasks
from .inputs import Job, jobs_from_inputs, settings_file_for
from .running import MANIFEST, run_batch, run_recording_task
from .settings import _check_settings, default_settings, flag_defaults, frames_text, settings_keys  # noqa: F401
from .summary import BatchSummary

__all__ = ["Task", "TaskOutcome", "run_tasks", "open_client", "Job", "jobs_from_inputs", "run_batch",
           "BatchSummary", "default_settings", "settings_keys", "settings_file_for", "MANIFEST", "flag_defaults",
           "frames_text", "run_recording_task", "WORKER_ENV"]
