"""The deployment files as written: systemd units rendered with a CADSPLAT_DATA, the example rig.toml, and the
documented flow (rig -> service -> twin) run against the paths they name (issue 58, item 10)."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from tests.conftest import REPO

UNITS = REPO / "deploy" / "systemd"
DATA, SPOOL = "/var/lib/cadsplat", "/var/spool/cadsplat"  # the data disk and the system disk's spool, as the files name them


def render_unit(path: Path, data: Path, spool: Path, rig_toml: Path) -> dict[str, list[str]]:
    """A unit's keys (each a list of its values), with Environment's CADSPLAT_DATA set to `data` and expanded
    as systemd does in ExecStart; `spool` and `rig_toml` stand in for the system paths the units name."""
    text = (
        path.read_text()
        .replace("\\\n", " ")
        .replace(DATA, str(data))
        .replace(SPOOL, str(spool))
        .replace("/etc/cadsplat/rig.toml", str(rig_toml))
    )
    keys: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            key, value = line.split("=", 1)
            keys.setdefault(key.strip(), []).append(value.strip())
    env = dict(kv.split("=", 1) for v in keys.get("Environment", []) for kv in shlex.split(v))
    assert env.get("CADSPLAT_DATA") == str(data), f"{path.name}: Environment=CADSPLAT_DATA is not the data directory"
    keys["ExecStart"] = [re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], v) for v in keys["ExecStart"]]
    return keys


def argv(unit: dict[str, list[str]]) -> list[str]:
    """The `cadsplat` arguments of a unit's ExecStart."""
    (cmd,) = unit["ExecStart"]
    words = shlex.split(cmd)
    assert words[0] == "/opt/cadsplat/.venv/bin/cadsplat"
    return words[1:]


def option(args: list[str], name: str) -> Path:
    return Path(args[args.index(name) + 1])


def writable(unit: dict[str, list[str]], path: Path) -> bool:
    """Whether ProtectSystem=strict lets the unit write `path` (under one of its ReadWritePaths)."""
    if unit.get("ProtectSystem") != ["strict"]:
        return True
    allowed = [Path(p.lstrip("-")) for v in unit.get("ReadWritePaths", []) for p in v.split()]
    return any(path == a or path.is_relative_to(a) for a in allowed)


@pytest.fixture
def deployed(tmp_path):
    """The units and the example rig.toml rendered for CADSPLAT_DATA=tmp/data, the spill's filesystem at tmp/spool."""
    from rig.config import load_config

    data, spool = tmp_path / "data", tmp_path / "spool"
    rig_toml = tmp_path / "etc" / "rig.toml"
    rig_toml.parent.mkdir()
    rig_toml.write_text((REPO / "deploy" / "rig.example.toml").read_text().replace(DATA, str(data)).replace(SPOOL, str(spool)))
    units = {p.stem.removeprefix("cadsplat-"): render_unit(p, data, spool, rig_toml) for p in sorted(UNITS.glob("*.service"))}
    return data, spool, load_config(rig_toml), units


def test_the_units_and_the_example_rig_toml_share_one_data_layout(deployed):
    data, _, cfg, units = deployed
    store, spill = cfg.storage.root, cfg.storage.spill
    rig, pipeline, check, kiosk = (units[k] for k in ("rig", "pipeline", "calibration-check", "kiosk"))
    # What the rig writes is what the pipeline and the nightly check read.
    assert option(argv(pipeline), "--store") == store
    assert option(argv(check), "--latest") == store / "captures"
    assert option(argv(rig), "--config") == option(argv(kiosk), "--config")
    # The spill is off the data disk, and every unit may write what it writes.
    assert spill is not None and not spill.is_relative_to(data)
    for unit, paths in (
        (rig, [store, spill]),
        (kiosk, [store, spill, option(argv(kiosk), "--work")]),
        (pipeline, [option(argv(pipeline), "--work")]),
        (check, [option(argv(check), "--calibration")]),
    ):
        assert all(writable(unit, p) for p in paths), (unit["Description"], paths, unit.get("ReadWritePaths"))
    # The kiosk runs the rig and its own pipeline: starting it stops the rig and pipeline services.
    conflicts = " ".join(kiosk["Conflicts"]).split()
    assert "cadsplat-rig.service" in conflicts and "cadsplat-pipeline.service" in conflicts


@pytest.mark.slow
def test_the_documented_flow_makes_a_twin_in_the_rendered_layout(deployed, library, monkeypatch, capsys):
    """rig (simulated, into rig.toml's store and spill) -> the pipeline unit's `service run` -> a twin under CADSPLAT_DATA."""
    from deploy.cli import main
    from deploy.jobs import JobStore
    from reconstruction import presets

    data, _, cfg, units = deployed
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "deploy.cli",
            "rig",
            "watch",
            "--simulate",
            "--store",
            str(cfg.storage.root),
            "--spill",
            str(cfg.storage.spill),
            "--trigger",
            "can",
            "--rate",
            "3",
            "--max-captures",
            "1",
            "--views",
            "4",
            "--size",
            "128",
            "96",
            "--min-free-gb",
            "0",
        ],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        cwd=REPO,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    shutil.copytree(library, data / "library")  # `cadsplat library build ... --out ${CADSPLAT_DATA}/library`
    original = presets.resolve_preset

    def short(name, stats):  # the preview preset with short stage caps: seconds, not minutes
        return replace(original(name, stats), iters_pose=20, iters_deform=10, iters_photo=20, dropout_anneal=10)

    monkeypatch.setattr("reconstruction.presets.resolve_preset", short)
    args = argv(units["pipeline"])
    assert len(list((option(args, "--store") / "captures").iterdir())) == 1  # the service reads where the rig wrote
    args[args.index("--preset") + 1] = "preview"
    capsys.readouterr()
    assert main([*args, "--max-jobs", "1", "--poll", "0.1", "--min-free-gb", "0"]) == 0
    out = capsys.readouterr().out
    (job,) = JobStore(data / "work" / "jobs.sqlite").jobs()
    assert job.status == "done", out
    twin = Path(job.steps["reconstruct"]["output"]["twin"])
    assert twin.is_relative_to(data / "work") and (twin / "manifest.json").is_file()
