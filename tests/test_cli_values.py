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


def test_version_flag_and_package_version(capsys):
    import turntable

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"turntable {turntable.__version__}"
    assert turntable.__version__ and turntable.__version__ != "0+unknown"  # installed: the metadata's version


def test_verbose_counts_before_and_after_the_command(tmp_path, caplog):
    import logging

    caplog.set_level(logging.DEBUG)
    assert main(["pattern", str(tmp_path / "a.pdf"), "--r-outer", "80", "--r-inner", "50"]) == 0
    assert logging.getLogger().level == logging.WARNING
    assert main(["-v", "pattern", str(tmp_path / "b.pdf"), "--r-outer", "80", "--r-inner", "50", "-v"]) == 0
    assert logging.getLogger().level == logging.DEBUG  # -v twice, one each side of the command


def test_importing_main_module_does_not_run_the_cli():
    import importlib

    importlib.import_module("turntable.__main__")  # would sys.exit() without the __name__ guard


def test_help_lists_commands_in_workflow_order_and_the_exit_codes(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    listed = [line.split()[0] for line in out.splitlines() if line.startswith("    ") and line.split()]
    order = [listed.index(c) for c in ("pattern", "calibrate", "calibrate-sequence", "reconstruct", "view")]
    assert order == sorted(order)
    assert "exit codes:" in out and "internal error" in out and "143 SIGTERM" in out


@pytest.mark.parametrize("command", ["pattern", "calibrate", "calibrate-sequence", "reconstruct", "view", "synth"])
def test_help_shows_defaults_and_no_raw_metavars(capsys, command):
    import re

    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = capsys.readouterr().out
    # a metavar made from an option's name with an underscore (STEP_DEG) reads as a variable, not a value
    assert not re.findall(r"--[a-z-]+ [A-Z]+_[A-Z_]+", text), text
    if command == "reconstruct":
        flat = " ".join(text.split())
        assert "--max-faces N" in flat and re.search(r"--max-faces N [^-]*default 50000", flat), flat
    if command == "synth":
        assert "--step-deg DEG" in text and "--distance-mm MM" in text


def test_threads_flag_before_or_after_the_command_sets_the_thread_pools(monkeypatch, tmp_path, capsys):
    import os

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    assert main(["pattern", str(tmp_path / "t.svg"), "--r-outer", "80", "--r-inner", "50", "--threads", "1"]) == 0
    assert os.environ["OMP_NUM_THREADS"] == "1" and os.environ["OPENBLAS_NUM_THREADS"] == "1"
    import cv2

    assert cv2.getNumThreads() == 1
    from recon.silhouettes import worker_threads

    assert worker_threads() == 1  # our own per-frame pool too
    assert main(["--threads", "2", "pattern", str(tmp_path / "u.svg"), "--r-outer", "80", "--r-inner", "50"]) == 0
    assert os.environ["OMP_NUM_THREADS"] == "2"
    cv2.setNumThreads(-1)
    with pytest.raises(SystemExit) as exc:
        main(["pattern", str(tmp_path / "v.svg"), "--r-outer", "80", "--r-inner", "50", "--threads", "0"])
    assert exc.value.code == 2 and "--threads" in capsys.readouterr().err
