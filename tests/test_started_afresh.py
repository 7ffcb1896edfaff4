"""A track's increment that started afresh (femreg.initial.previous_or_fresh) is a flag of its result, saved with
it: the track's retry rule and the command line read the flag, not the message; files written before the flag
existed say it in the message only, and are read that way."""
from types import SimpleNamespace

import numpy as np
import pytest
from skfem import MeshQuad1

import femreg
from femreg.errors import FileFormatError
from femreg.initial import FRESH_NOTE
from femreg.repair import retry_flagged


def _result(**kw):
    mesh = MeshQuad1.init_tensor(np.linspace(0.0, 2.0, 3), np.linspace(0.0, 2.0, 3))
    return femreg.RegistrationResult(mesh, np.zeros(2 * mesh.p.shape[1]), shape=(11, 11), spacing=(0.2, 0.2),
                                     origin=(0.0, 0.0), success=True, message="converged", **kw)


@pytest.mark.parametrize("flag", [True, False])
def test_flag_survives_saving_and_loading(tmp_path, flag):
    path = _result(started_afresh=flag).save(tmp_path / "r.npz")
    with np.load(path) as z:
        assert z["started_afresh"].dtype == bool and bool(z["started_afresh"]) is flag
    assert femreg.load_result(path).started_afresh is flag


def test_the_flag_not_the_message_decides(tmp_path):
    # a message naming the words (a user's note, a later note) does not make a fresh start
    r = _result(started_afresh=False)
    r.message = f"converged; {FRESH_NOTE}? no"
    assert femreg.load_result(r.save(tmp_path / "r.npz")).started_afresh is False


@pytest.mark.parametrize("message, expected", [(f"converged; {FRESH_NOTE}: the frames match better", True),
                                               ("converged", False)])
def test_files_without_the_key_read_the_message(tmp_path, message, expected):
    r = _result(started_afresh=not expected)
    r.message = message
    path = r.save(tmp_path / "r.npz")
    with np.load(path) as z:
        d = {k: z[k] for k in z.files if k != "started_afresh"}
    np.savez(tmp_path / "old.npz", **d)        # as an earlier version wrote it
    assert femreg.load_result(tmp_path / "old.npz").started_afresh is expected


def test_a_bad_flag_is_refused_naming_the_key(tmp_path):
    path = _result().save(tmp_path / "r.npz")
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d["started_afresh"] = np.str_("yes")
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(FileFormatError, match="started_afresh"):
        femreg.load_result(tmp_path / "bad.npz")


def test_volume_results_never_started_afresh():
    from femreg.volume_result import VolumeResult

    assert VolumeResult.started_afresh is False


@pytest.mark.parametrize("afresh, calls", [(True, 1), (False, 2)])
def test_retry_follows_the_flag(afresh, calls):
    # a failed increment is retried from the fresh start unless it already started afresh; the message names the
    # words in both cases, so only the flag can tell them apart
    starts = []

    def register_from(start):
        starts.append(start)
        res = SimpleNamespace(success=False, message=f"FAILED: low NCC; {FRESH_NOTE}", ncc_after=0.3,
                              started_afresh=afresh if start == "previous" else False)
        return res, np.zeros(2)

    res, _, note = retry_flagged(register_from, "previous", "fresh", False, 0.5, 2)
    assert starts == ["previous", "fresh"][:calls]
    assert bool(note) is (not afresh)
