"""`femreg track` when a frame fails mid-run: earlier frames stay on disk, exit code 1 names the frame, and a
--resume run completes with the same result as an uninterrupted one (nothing lost, nothing recomputed)."""
import numpy as np
import pytest

import femreg.sequence
from femreg.cli import main
from _track_loop import ARGS, write_loop

@pytest.fixture(scope="module")
def npy_sequence(tmp_path_factory):
    return write_loop(tmp_path_factory.mktemp("seq") / "frames.npy")


def _fail_at_call(monkeypatch, n_fail, exc):
    """Make the n-th call of register inside femreg.track raise ``exc``."""
    real = femreg.sequence.register
    calls = {"n": 0}

    def flaky(*a, **kw):
        calls["n"] += 1
        if calls["n"] == n_fail:
            raise exc
        return real(*a, **kw)

    monkeypatch.setattr(femreg.sequence, "register", flaky)
    return calls


@pytest.fixture(scope="module")
def uninterrupted(npy_sequence, tmp_path_factory):
    """The reference runs, one per mode."""
    out = {}
    for mode in ("accumulate", "direct"):
        out[mode] = tmp_path_factory.mktemp(mode)
        assert main(["track", str(npy_sequence), "-o", str(out[mode]), "--mode", mode] + ARGS) == 0
    return out


# ValueError covers the numerical failures (numpy's LinAlgError is one): they must not be mistaken for bad input.
@pytest.mark.parametrize("mode, exc", [("accumulate", RuntimeError("solver blew up")),
                                       ("accumulate", np.linalg.LinAlgError("singular matrix")),
                                       ("direct", ValueError("energy of the initial guess is not finite"))])
def test_failed_frame_keeps_earlier_frames_and_resume_completes(npy_sequence, uninterrupted, tmp_path, capsys,
                                                                 monkeypatch, mode, exc):
    full, part = uninterrupted[mode], tmp_path / "part"
    calls = _fail_at_call(monkeypatch, 3, exc)
    capsys.readouterr()
    rc = main(["track", str(npy_sequence), "-o", str(part), "--mode", mode] + ARGS)
    err = capsys.readouterr().err
    assert rc == 1, f"exit {rc}, stderr {err!r}"
    assert err.startswith("femreg track: failed: frame 3 could not be computed"), err
    assert "frames 1-2 are saved" in err and "--resume" in err, err
    assert "Traceback" not in err and err.strip().count("\n") == 0, err
    assert calls["n"] == 3
    # Frames 1 and 2 are complete files (loadable, equal to the uninterrupted run); nothing half-written.
    assert sorted(p.name for p in part.iterdir()) == ["frame_001.npz", "frame_002.npz", "track.json"]
    kept = {k: femreg.load_result(part / f"frame_{k:03d}.npz") for k in (1, 2)}
    mtimes = {p.name: p.stat().st_mtime_ns for p in part.glob("frame_*.npz")}
    for k, r in kept.items():
        assert np.array_equal(r.u, np.load(full / f"frame_{k:03d}.npz")["u"]), f"frame {k} differs"

    monkeypatch.undo()
    assert main(["track", str(npy_sequence), "-o", str(part), "--mode", mode, "--resume"] + ARGS) == 0
    out = capsys.readouterr().out
    assert "2 computed, 2 resumed" in out, out
    assert {p.name: p.stat().st_mtime_ns for p in part.glob("frame_00[12].npz")} == mtimes
    for k in (1, 2, 3, 4):
        a = np.load(full / f"frame_{k:03d}.npz")
        b = np.load(part / f"frame_{k:03d}.npz")
        assert np.array_equal(a["u"], b["u"]), f"frame {k} differs after resume"


def test_bad_input_still_exit_2(npy_sequence, tmp_path, capsys):
    assert main(["track", str(npy_sequence), "-o", str(tmp_path), "--alpha", "nan"] + ARGS[:2] + ARGS[4:]) == 2
    err = capsys.readouterr().err
    assert "alpha" in err and "failed" not in err, err
