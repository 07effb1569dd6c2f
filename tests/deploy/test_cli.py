import os
import subprocess
import sys

from deploy.cli import COMMANDS, main
from reconstruction.parallel import OPENMP_SPIN_COUNT


def test_help_lists_every_command_without_importing_them(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_help_is_cheap_in_a_fresh_process():
    code = "import sys; from deploy.cli import main; main(['--help']); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("False")


def test_torch_loads_with_openmp_workers_that_spin_briefly_unless_the_user_chose():
    code = "import os; from deploy.cli import main; print(os.environ.get('GOMP_SPINCOUNT'))"
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip() == str(OPENMP_SPIN_COUNT)
    passive = {**env, "OMP_WAIT_POLICY": "PASSIVE"}
    out = subprocess.run([sys.executable, "-c", code], env=passive, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "None"


def test_version(capsys):
    assert main(["--version"]) == 0
    assert "cadsplat, version" in capsys.readouterr().out


def test_unknown_command_is_one_sentence_and_nonzero(capsys):
    assert main(["no-such-command"]) != 0
    assert "No such command" in capsys.readouterr().err
