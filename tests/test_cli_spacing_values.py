"""--spacing takes two values (frames: axial, lateral) or three (volumes: and the elevational plane spacing), mm:
other counts are argparse's exit 2 naming the count; files written after the option's values stay the command's."""
import numpy as np
import pytest

from femreg.cli import build_parser, main


def _parsed(argv):
    args, extra = build_parser(argv).parse_known_args(argv)
    return args, extra


@pytest.mark.parametrize("values", [["0.02"], ["0.02", "0.2", "0.25", "0.3"], ["0.02"] * 6])
@pytest.mark.parametrize("command", ["register", "track", "info"])
def test_one_or_four_and_more_values_are_refused_naming_the_count(tmp_path, capsys, command, values):
    with pytest.raises(SystemExit) as exc:
        main([command, str(tmp_path / "f.npy"), "--spacing", *values])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert exc.value.code == 2
    assert f"argument --spacing: expected 2 arguments (DX DY) or 3 for volumes (DX DY DZ), got {len(values)}" in err
    assert "--spacing DX DY DZ" in err and "--spacing DR auto" in err, err


@pytest.mark.parametrize("values, expected", [(["0.02", "0.2"], [0.02, 0.2]), (["0.02", "auto"], [0.02, None]),
                                              (["0.025", "0.2", "0.25"], [0.025, 0.2, 0.25])])
def test_two_or_three_values_are_taken(values, expected):
    args, extra = _parsed(["register", "ref.npy", "mov.npy", "-o", "r.npz", "--spacing", *values])
    assert args.spacing == expected and extra == []


@pytest.mark.parametrize("values", [["0.02", "0.2"], ["0.025", "0.2", "0.25"]])
def test_files_after_the_values_stay_the_command_s(values):
    # argparse alone gives an option of 2 or 3 values every word up to the next option, the files too
    args, extra = _parsed(["register", "--spacing", *values, "ref.npy", "mov.npy", "-o", "r.npz"])
    assert (args.reference, args.moving, args.output) == ("ref.npy", "mov.npy", "r.npz"), vars(args)
    assert args.spacing == [float(v) for v in values] and extra == []
    args, extra = _parsed(["track", "loop.npy", "--spacing", *values, "-o", "run"])
    assert args.file == "loop.npy" and len(args.spacing) == len(values) and extra == []


def test_a_value_written_with_a_comma_is_named_not_taken_for_a_file(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["register", "--spacing", "0,02", "0.2", "ref.npy", "mov.npy", "-o", "r.npz"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "write it with a decimal point, 0.02" in err, err


def test_three_values_for_frames_are_refused_naming_volume(tmp_path, capsys):
    path = tmp_path / "f.npy"
    np.save(path, np.zeros((3, 64, 16), np.float32))
    rc = main(["register", str(path), "--pair", "0", "1", "-o", str(tmp_path / "r.npz"),
               "--spacing", "0.02", "0.2", "0.25"])
    err = capsys.readouterr().err
    assert rc == 2 and "three values (DX DY DZ) is for RF volumes" in err and "--volume" in err, err
    assert not (tmp_path / "r.npz").exists()


def test_help_shows_the_counts(capsys):
    with pytest.raises(SystemExit):
        main(["register", "--help"])
    assert "--spacing DX DY [DZ]" in capsys.readouterr().out
