import subprocess
import sys

from sc6d_jax import __version__
from sc6d_jax.cli import COMMANDS, main


def test_help_lists_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_version(capsys):
    assert main(["--version"]) == 0
    assert __version__ in capsys.readouterr().out


def test_unknown_command_exits_nonzero(capsys):
    assert main(["no-such-command"]) == 2
    assert "unknown command" in capsys.readouterr().err


def test_console_entry_point_installed():
    out = subprocess.run(
        [sys.executable, "-m", "sc6d_jax.cli", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == f"sc6d {__version__}"
