"""Impossible numbers are refused at the command line, naming the flag, before any work (issue 10)."""

import pytest

from turntable.cli import main


@pytest.mark.parametrize("argv, message", [
    (["reconstruct", "IMAGES", "--r-outer", "80", "--r-inner", "50", "--step-deg", "0"],
     "--step-deg must be a non-zero"),
    (["reconstruct", "IMAGES", "--r-outer", "80", "--r-inner", "50", "--step-deg", "nan"],
     "--step-deg must be a non-zero"),
    (["reconstruct", "IMAGES", "--r-outer", "inf", "--r-inner", "50"], "--r-outer must be a positive number"),
    (["reconstruct", "IMAGES", "--r-outer", "80", "--r-inner", "-50"], "--r-inner must be a positive number"),
    (["reconstruct", "IMAGES", "--r-outer", "80", "--r-inner", "50", "--stroke", "0"], "--stroke must be a positive"),
    (["calibrate-sequence", "IMAGES", "--r-outer", "80", "--r-inner", "50", "--principal-point", "nan", "nan",
      "--out", "OUT/c.json"], "--principal-point must be two finite"),
    (["calibrate", "IMAGES/a.jpg", "--r-outer", "80", "--r-inner", "50", "--principal-point", "1", "inf"],
     "--principal-point must be two finite"),
])
def test_impossible_numbers_are_refused_naming_the_flag(tmp_path, capsys, argv, message):
    (tmp_path / "IMAGES").mkdir()
    (tmp_path / "OUT").mkdir()
    argv = [a.replace("IMAGES", str(tmp_path / "IMAGES")).replace("OUT", str(tmp_path / "OUT")) for a in argv]
    if argv[0] == "reconstruct":
        argv += ["--out", str(tmp_path / "out")]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2 and message in err, err
    assert "Traceback" not in err and "internal error" not in err


def test_an_internal_error_has_its_own_exit_code(monkeypatch, capsys, tmp_path):
    """A bug of ours exits 4 with one line (not 1, which means "finished, some inputs failed")."""
    import turntable.cli.pattern

    def boom(args):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(turntable.cli.pattern, "run", boom)
    code = main(["pattern", str(tmp_path / "t.pdf")])
    err = capsys.readouterr().err
    assert code == 4 and "internal error: RuntimeError: simulated bug" in err and "Traceback" not in err
