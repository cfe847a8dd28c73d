"""The fftune console entry point."""
import subprocess
import sys

from fftune.host.cli import main


def test_version_flag_prints_version(capsys):
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert "fftune 0.1.0" in capsys.readouterr().out


def test_no_command_prints_help_and_fails(capsys):
    assert main([]) == 2
    assert "usage: fftune" in capsys.readouterr().out


def test_unknown_subcommand_is_rejected():
    proc = subprocess.run([sys.executable, "-m", "fftune.host.cli", "no-such-command"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "invalid choice" in proc.stderr
    assert "Traceback" not in proc.stderr
