import subprocess
import sys

from deploy.cli import COMMANDS, main


def test_help_lists_every_command_without_importing_them(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_help_is_cheap_in_a_fresh_process():
    code = "import sys; from deploy.cli import main; main(['--help']); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("False")


def test_version(capsys):
    assert main(["--version"]) == 0
    assert "cadsplat, version" in capsys.readouterr().out


def test_unknown_command_is_one_sentence_and_nonzero(capsys):
    assert main(["no-such-command"]) != 0
    assert "No such command" in capsys.readouterr().err
