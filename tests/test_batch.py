"""femreg.batch / `femreg batch`: Dask batches give the serial results bitwise, survive a killed worker, resume
without recomputing, record a failing recording while the others finish, and exit 0 / 1 / 2.

One 2-worker LocalCluster serves the whole module (starting one costs a few seconds); the recordings are tiny
synthetic speckle sequences (200 x 40 pixels, 3 frames, 3 mm mesh: ~0.1 s per task).
"""
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import femreg  # noqa: E402
from femreg.batch import Job, Task, jobs_from_inputs, run_batch, run_tasks  # noqa: E402
from femreg.cli import main  # noqa: E402
from femreg.errors import InputError  # noqa: E402
from femreg.synthetic import speckle_image, warp_image  # noqa: E402

SPACING = (0.05, 0.2)
N_REC = 8
SETTINGS = {"element_size": 3.0, "regularizer": "momentum-stress"}


def _recording(seed: int) -> np.ndarray:
    """3 frames, axial compression 0.25 % per frame plus a little lateral expansion."""
    rng = np.random.default_rng(seed)
    ref = speckle_image((200, 40), SPACING, rng)
    s = 0.0025 * (1 + 0.1 * seed)
    frames = [ref] + [warp_image(ref, SPACING, (0, 0), lambda p, k=k: np.column_stack(
        [-k * s * p[:, 0], 0.3 * k * s * (p[:, 1] - 4.0)])) for k in (1, 2)]
    return np.stack(frames)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("recordings")
    for k in range(N_REC):
        np.savez(d / f"rec{k:02d}.npz", rf=_recording(k), spacing=np.array(SPACING))
    return d


@pytest.fixture(scope="module")
def client():
    import cloudpickle
    import dask

    from femreg.batch import open_client

    # The worker plugin below is defined here, in a module the workers do not import: ship it by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    # allowed-failures 1: a task whose worker dies twice is given up (KilledWorker) after 2 restarts, not 4
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}), open_client(2) as cl:
        yield cl


@pytest.fixture(scope="module")
def serial(data_dir, tmp_path_factory):
    """The reference: the same batch run serially in this process (no Dask)."""
    out = tmp_path_factory.mktemp("serial")
    summary = run_batch(jobs_from_inputs([data_dir], SETTINGS), out, workers=0, progress=False)
    assert summary.ok and summary.n_computed == N_REC, summary.failed
    return out


def _arrays(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _assert_same_outputs(a: Path, b: Path):
    files = sorted(p.relative_to(a) for p in a.glob("*/*.npz"))
    assert files and files == sorted(p.relative_to(b) for p in b.glob("*/*.npz"))
    for f in files:
        x, y = _arrays(a / f), _arrays(b / f)
        assert x.keys() == y.keys(), f
        for k in x:
            assert np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f"), f"{f}: {k} differs"


def test_two_worker_cluster_matches_serial_bitwise(data_dir, serial, client, tmp_path):
    out = tmp_path / "dask"
    summary = run_batch(jobs_from_inputs([data_dir], SETTINGS), out, client=client, progress=False)
    assert summary.ok and summary.n_computed == N_REC, summary.failed
    _assert_same_outputs(serial, out)
    # Both workers took tasks, each with one BLAS thread; memory per task is reported.
    workers = {r["worker"] for r in summary.records}
    assert len(workers) == 2, workers
    assert {r["blas_threads"] for r in summary.records} == {"1"}
    # measured 125-135 MiB per worker process for these tiny recordings
    assert all(50 < r["peak_rss_mb"] < 2000 for r in summary.records), [r["peak_rss_mb"] for r in summary.records]
    # The batch computes what the library computes: femreg.track with the same settings, in this process.
    rf = np.load(data_dir / "rec03.npz")["rf"]
    direct = femreg.track(rf, spacing=SPACING, element_size=3.0)
    assert np.array_equal(direct[-1].u, femreg.load_result(out / "rec03" / "frame_002.npz").u)
    # Deterministic names, manifest, and the summary tables.
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == [f"rec{k:02d}" for k in range(N_REC)]
    manifest = json.loads((out / "batch.json").read_text())
    assert manifest["tasks"]["rec00/track"]["settings"]["element_size"] == 3.0
    csv_lines = (out / "summary.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + N_REC and csv_lines[1].startswith("rec00/track,ok,True")
    assert "| rec07/track | ok |" in (out / "summary.md").read_text()


def test_resume_recomputes_nothing_and_refuses_changed_settings(data_dir, client, tmp_path):
    out = tmp_path / "out"
    jobs = jobs_from_inputs([data_dir], SETTINGS)
    first = run_batch(jobs[:5], out, client=client, progress=False)
    assert first.n_computed == 5
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("*/*") if p.is_file()}
    with pytest.raises(InputError, match="already holds a batch"):
        run_batch(jobs, out, client=client, progress=False)
    again = run_batch(jobs[:5], out, client=client, resume=True, progress=False)
    assert again.n_computed == 0 and again.ok
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps, "a finished result was rewritten"
    more = run_batch(jobs, out, client=client, resume=True, progress=False)  # three more recordings
    assert more.n_computed == N_REC - 5 and more.ok
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    changed = jobs_from_inputs([data_dir], {**SETTINGS, "alpha": 0.5})
    with pytest.raises(InputError, match=r"settings or inputs changed .*alpha"):
        run_batch(changed, out, client=client, resume=True, progress=False)


def test_failing_recording_is_recorded_and_others_finish(data_dir, client, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for k in (0, 1):
        (src / f"rec{k:02d}.npz").write_bytes((data_dir / f"rec{k:02d}.npz").read_bytes())
    (src / "broken.npz").write_bytes(b"PK\x03\x04 not really a zip archive")
    np.savez(src / "single.npz", rf=_recording(0)[:1], spacing=np.array(SPACING))  # one frame: cannot track
    out = tmp_path / "out"
    summary = run_batch(jobs_from_inputs([src], SETTINGS), out, client=client, progress=False)
    status = {r["key"]: r["status"] for r in summary.records}
    assert status == {"broken/track": "failed", "rec00/track": "ok", "rec01/track": "ok", "single/track": "failed"}
    errors = {r["key"]: r["error"] for r in summary.failed}
    assert "broken.npz" in errors["broken/track"] and "FileFormatError" in errors["broken/track"], errors
    assert "at least 2 frames" in errors["single/track"], errors
    assert json.loads((out / "broken" / "track.record.json").read_text())["status"] == "failed"
    # Fixing the input and resuming reruns the failed tasks only.
    (src / "broken.npz").write_bytes((data_dir / "rec02.npz").read_bytes())
    (src / "single.npz").unlink()
    again = run_batch(jobs_from_inputs([src], SETTINGS), out, client=client, resume=True, progress=False)
    assert again.ok and again.n_computed == 1, again.records


def test_register_pairs_one_task_each(data_dir, client, tmp_path):
    jobs = jobs_from_inputs([data_dir / "rec01.npz"], {**SETTINGS, "task": "register", "pairs": [[0, 1], [0, 2]]})
    summary = run_batch(jobs, tmp_path / "out", client=client, progress=False)
    assert [r["key"] for r in summary.records] == ["rec01/pair_000-001", "rec01/pair_000-002"] and summary.ok
    rf = np.load(data_dir / "rec01.npz")["rf"]
    direct = femreg.register(rf[0], rf[2], spacing=SPACING, element_size=3.0)
    saved = femreg.load_result(tmp_path / "out" / "rec01" / "pair_000-002.npz")
    assert np.array_equal(direct.u, saved.u)


def test_cli_exit_codes_and_settings_file(data_dir, client, tmp_path, capsys):
    addr = client.scheduler.address
    src = tmp_path / "in"
    src.mkdir()
    for k in (0, 1):
        (src / f"rec{k:02d}.npz").write_bytes((data_dir / f"rec{k:02d}.npz").read_bytes())
    (src / "rec01.femreg.toml").write_text('regularizer = "strain"\nalpha = 2.0\n')
    base = ["batch", str(src), "--scheduler", addr, "--element-size", "3", "--no-progress"]
    assert main(base + ["-o", str(tmp_path / "ok")]) == 0
    out = capsys.readouterr().out
    assert "2 task(s)" in out and "0 failed" in out, out
    r1 = femreg.load_result(tmp_path / "ok" / "rec01" / "frame_002.npz")
    r0 = femreg.load_result(tmp_path / "ok" / "rec00" / "frame_002.npz")
    assert (r1.regularizer, r1.alpha, r0.regularizer) == ("strain", 2.0, "momentum-stress")
    assert main(base + ["-o", str(tmp_path / "ok"), "--resume"]) == 0
    assert "0 computed, 2 kept" in capsys.readouterr().out
    # a failing recording: exit 1, named on stderr
    (src / "bad.npz").write_bytes(b"garbage")
    assert main(base + ["-o", str(tmp_path / "fail")]) == 1
    assert "FAILED bad/track" in capsys.readouterr().err
    (src / "bad.npz").unlink()
    # bad input: exit 2 before anything runs
    assert main(["batch", str(tmp_path / "missing"), "-o", str(tmp_path / "x"), "--workers", "0"]) == 2
    (src / "rec00.femreg.json").write_text('{"regulariser": "strain"}')
    assert main(base + ["-o", str(tmp_path / "y")]) == 2
    err = capsys.readouterr().err
    assert "unknown setting(s) ['regulariser']" in err and "rec00.femreg.json" in err, err
    assert not (tmp_path / "y").exists()
    (src / "rec00.femreg.json").write_text('{"alpha": -1}')
    assert main(base + ["-o", str(tmp_path / "y")]) == 2
    assert "--alpha must be a finite number" in capsys.readouterr().err


def test_names_are_deterministic_and_unique(tmp_path):
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        np.savez(tmp_path / sub / "scan.npz", rf=np.zeros((2, 4, 4)))
    (tmp_path / "a" / "frames").mkdir()
    (tmp_path / "a" / ".hidden.npz").write_bytes(b"")
    (tmp_path / "a" / "notes.txt").write_text("not a recording")
    jobs = jobs_from_inputs([tmp_path / "b", tmp_path / "a"])
    assert [j.name for j in jobs] == ["b__scan", "frames", "a__scan"]
    assert jobs == jobs_from_inputs([tmp_path / "b", tmp_path / "a"])
    with pytest.raises(InputError, match="no recordings"):
        jobs_from_inputs([tmp_path / "a" / "frames"])
    one = jobs_from_inputs([tmp_path / "a" / "frames"], folders="recording")
    assert [j.name for j in one] == ["frames"]
    with pytest.raises(InputError, match="job names must be unique"):
        run_batch([Job(str(tmp_path / "a" / "scan.npz"), "x"), Job(str(tmp_path / "b" / "scan.npz"), "x")],
                  tmp_path / "out", workers=0)


def _fail_on_odd(i):
    if i % 2:
        raise RuntimeError(f"odd {i}")
    return i * 10


def test_run_tasks_reports_errors_and_keeps_order():
    got = run_tasks([Task(f"t{i}", _fail_on_odd, (i,), priority=i) for i in range(4)], workers=0, progress=False)
    assert list(got) == ["t0", "t1", "t2", "t3"]
    assert [o.value for o in got.values()] == [0, None, 20, None]
    assert got["t1"].error == "RuntimeError: odd 1"


def test_study_cases_on_dask_match_serial(client, tmp_path):
    """The study's runner (paperstudy.study.run_cases) on the cluster writes the serial run's records bitwise."""
    study = pytest.importorskip("paperstudy.study")
    s = study.StudySettings(n_frames=4, sequence_options={"depth_mm": 42.0, "width_mm": 24.0},
                            crop_mm=(18.0, 42.0, -10.0, 10.0), element_size=3.0, name="test")
    specs = [study.make_case(s, "pair", "plane-stress-HI", r, a, (0, 3))
             for r, a in (("strain", 10.0), ("momentum-stress", 1.0))]
    serial = study.run_cases(specs, tmp_path / "serial", jobs=1, progress=False)
    dask_ = study.run_cases(specs, tmp_path / "dask", client=client, progress=False)
    assert all("error" not in r for r in serial.values()), serial
    for sp in specs:
        a, b = serial[sp["key"]], dask_[sp["key"]]
        assert a["metrics"] == b["metrics"] and a["nit"] == b["nit"]
        za = _arrays(tmp_path / "serial" / "cases" / f"{sp['key']}.npz")
        zb = _arrays(tmp_path / "dask" / "cases" / f"{sp['key']}.npz")
        assert all(np.array_equal(za[k], zb[k]) for k in za)
    again = study.run_cases(specs, tmp_path / "dask", client=client, progress=False, stats=(st := {}))
    assert st["computed"] == 0 and again.keys() == dask_.keys()


# The worker-killing tests last: the workers they restart re-import femreg (a few seconds each).
class _KillOnce(distributed.WorkerPlugin):
    """Kills the worker process the first time a task whose key contains ``match`` starts executing (every time
    with ``always``)."""

    def __init__(self, marker, match, always=False):
        self.marker, self.match, self.always = str(marker), match, always

    def transition(self, key, start, finish, **kw):
        if finish == "executing" and self.match in str(key) and (self.always or not os.path.exists(self.marker)):
            with open(self.marker, "a") as fh:
                fh.write(f"{os.getpid()}\n")
            os._exit(1)


def test_killed_worker_loses_nothing_and_batch_completes(data_dir, serial, client, tmp_path):
    marker = tmp_path / "killed"
    client.register_plugin(_KillOnce(marker, "rec05/track"), name="kill-once")
    try:
        summary = run_batch(jobs_from_inputs([data_dir], SETTINGS), tmp_path / "out", client=client,
                            progress=False)
    finally:
        client.unregister_worker_plugin("kill-once")
    assert marker.exists(), "the worker was not killed: the test tested nothing"
    killed_pid = marker.read_text().strip()
    assert summary.ok, summary.failed
    rec5 = next(r for r in summary.records if r["key"] == "rec05/track")
    assert not rec5["worker"].endswith(f":{killed_pid}"), "the killed task must have been rerun elsewhere"
    _assert_same_outputs(serial, tmp_path / "out")
    # Each record is written once per computation; a task whose worker died after finishing it is not rerun.
    assert sum(r["computed"] for r in summary.records) + sum(not r["computed"] for r in summary.records) == N_REC
    client.wait_for_workers(2, timeout=30)


def test_task_that_keeps_killing_its_worker_is_recorded_as_failed(data_dir, client, tmp_path):
    marker = tmp_path / "killed"
    client.register_plugin(_KillOnce(marker, "rec01/track", always=True), name="kill-always")
    try:
        summary = run_batch(jobs_from_inputs([data_dir / "rec00.npz", data_dir / "rec01.npz"], SETTINGS),
                            tmp_path / "out", client=client, progress=False)
    finally:
        client.unregister_worker_plugin("kill-always")
    assert len(marker.read_text().split()) == 2, "allowed-failures 1: two deaths, then given up"
    assert [r["status"] for r in summary.records] == ["ok", "failed"]
    assert "KilledWorker" in summary.records[1]["error"], summary.records[1]
    rec = json.loads((tmp_path / "out" / "rec01" / "track.record.json").read_text())
    assert rec["status"] == "failed" and "KilledWorker" in rec["error"]
    client.wait_for_workers(2, timeout=30)
