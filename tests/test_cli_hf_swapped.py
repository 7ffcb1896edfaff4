"""A 15 MHz linear probe's int16 HDF5 loop (frames first, per-frame time stamps, the acquisition in attributes)
given its axial and lateral spacings exchanged.  What used to trip: the echo search ran on the exchanged frame (a
sliver 1.6 mm wide, over 90 mm deep) before the orientation check and refused it as "the echo region -0.01 to 1.64
mm is too small for a mesh inside the margin" (no word of the swap); `track` and `elastogram` printed "the RF
carrier reads 1.92 MHz ... the axial spacing is too large" before refusing the swap.  Three small simulated frames
(forward.pairs, 1 % compression each), 0-12 mm, the echo meeting the noise at 9 mm."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

import femreg
from femreg.cli import main
from femreg.orientation import OrientationError

F0, FS, PITCH = 15.0, 60.0, 0.1         # MHz, MHz, mm
DX = 1540.0 * 1e-3 / (2 * FS)           # mm


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    from forward import fields as F
    from forward.pairs import Probe, alpha_for_floor, attenuation_gain_db, make_sequence

    seq = make_sequence(F.compression(0.0), Probe(F0, FS, PITCH, 0.3, 2.0, name="L15"), size_mm=(12.0, 12.8),
                        snr_db=30.0, seed=0, n_frames=3, step=0.01, top_mm=0.0,
                        echo_gain_db=attenuation_gain_db(alpha_for_floor(9.0, 30.0, F0), F0))
    frames = np.asarray(seq.frames)
    path = tmp_path_factory.mktemp("hf") / "hf.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("rf", data=np.round(frames * (20000 / np.abs(frames).max())).astype("<i2"))
        f.create_dataset("timestamps", data=1.7e9 + np.array([0.0, 0.0254, 0.0497]))
        f.attrs.update(sampling_frequency=FS * 1e6, center_frequency=F0 * 1e6, element_pitch=PITCH * 1e-3,
                       sound_speed=1540.0)
    return {"frames": frames, "path": path}


def test_register_names_the_swap_not_the_echo_sliver(loop):
    ref, mov = loop["frames"][:2]
    with pytest.raises(OrientationError, match=r"look swapped: pass spacing \(0\.012833.*, 0\.1\)") as err:
        femreg.register(ref, mov, spacing=(PITCH, DX))
    assert err.value.problem == "swapped" and "too small for a mesh" not in str(err.value)


@pytest.mark.parametrize("command", ["register", "track", "elastogram"])
def test_the_commands_refuse_the_swap_with_one_line(loop, tmp_path, capsys, command):
    out = ["-o", tmp_path / "r.npz", "--pair", 0, 1] if command == "register" else ["-o", tmp_path / "run"]
    rc = main([command, str(loop["path"]), "--spacing", f"{PITCH}", f"{DX:.5g}", "--no-progress", *map(str, out)])
    err = capsys.readouterr().err
    assert rc == 2 and "look swapped: pass --spacing 0.012833 0.1" in err, err
    assert "RF carrier reads" not in err and "too small for a mesh" not in err and err.count("\n") == 1, err


def test_the_right_spacing_registers(loop, tmp_path, capsys):
    out = tmp_path / "r.npz"
    rc = main(["register", str(loop["path"]), "--pair", "0", "1", "--spacing", f"{DX:.5g}", f"{PITCH}",
               "--no-progress", "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    exx = femreg.load_result(out).on_grid()["exx"]
    assert abs(np.nanmedian(exx) + 0.01) < 0.0005, np.nanmedian(exx)      # measured -1.00 %
