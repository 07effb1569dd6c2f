"""benchmarks/ is a package run with `python -m benchmarks.<name>`: no script edits sys.path, no script
name can shadow (or be mistaken for) a module of the packages, and every script imports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BENCHMARKS = REPO / "benchmarks"
PACKAGES = ("calibration", "rig", "reconstruction", "simulation", "deploy")


def benchmark_modules() -> list[str]:
    return sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem != "__init__")


def test_no_benchmark_edits_sys_path():
    offenders = [p.name for p in BENCHMARKS.rglob("*.py") if "sys.path" in p.read_text()]
    assert not offenders, offenders


def test_no_benchmark_name_shadows_a_package_module():
    package_modules = set(PACKAGES) | {p.stem for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}
    package_modules |= {p.parent.name for pkg in PACKAGES for p in (REPO / pkg).rglob("__init__.py")}
    names = benchmark_modules()
    assert names and not set(names) & package_modules, set(names) & package_modules
    # Scripts are bench_<thing>; helpers shared between them are private (_common).
    assert all(n.startswith(("bench_", "_")) for n in names), names


def test_every_benchmark_module_imports():
    """Import only (nothing runs: each script's work is under `if __name__ == "__main__"`), in a child
    process so import-time settings (MUJOCO_GL) stay out of the test session."""
    mods = [f"benchmarks.{n}" for n in benchmark_modules()]
    code = (
        "import importlib, sys\nfailed = []\nfor m in sys.argv[1:]:\n    try:\n        importlib.import_module(m)\n"
        "    except Exception as e:\n        failed.append(f'{m}: {e!r}')\nprint('\\n'.join(failed))\nsys.exit(1 if failed else 0)\n"
    )
    res = subprocess.run([sys.executable, "-c", code, *mods], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
