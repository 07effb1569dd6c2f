"""`cadsplat rig ...` as a user runs it (subprocesses; the simulated rig renders tiny images)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from tests.conftest import REPO
from tests.rig.conftest import assert_store_sound

SMALL = ["--views", "3", "--size", "96", "72", "--min-free-gb", "0"]


def _cadsplat(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from deploy.cli import main; sys.exit(main())", *args]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def _committed(stdout: str) -> list[str]:
    return [line.split()[1] for line in stdout.splitlines() if line.startswith("committed ")]


@contextmanager
def watching(store: Path, *args: str):
    """`rig watch --simulate` on `store` (a subprocess), yielded once it has committed its first capture; on exit it
    is stopped with SIGTERM and `.result` holds (returncode, stdout, stderr)."""
    proc = subprocess.Popen(
        _cadsplat("rig", "watch", "--simulate", "--trigger", "can", "--store", str(store), *(args or ("--rate", "4", *SMALL))),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        cwd=REPO,
    )
    lines = []
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and not (lines and lines[-1].startswith("committed")):
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
        assert lines and lines[-1].startswith("committed"), "".join(lines)
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
        proc.result = (proc.returncode, "".join(lines) + out, err)


def test_watch_simulate_can_ends_after_max_captures(tmp_path):
    store = tmp_path / "store"
    r = subprocess.run(
        _cadsplat("rig", "watch", "--simulate", "--trigger", "can", "--rate", "3", "--max-captures", "2", "--store", str(store), *SMALL),
        capture_output=True,
        text=True,
        env=_env(),
        cwd=REPO,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr
    ids = _committed(r.stdout)
    assert len(ids) == 2 and assert_store_sound(store, ids) == sorted(ids)
    assert "captures 2 | quarantined 0" in r.stderr


def test_watch_simulate_serial_stops_cleanly_on_sigterm(tmp_path):
    store = tmp_path / "store"
    proc = subprocess.Popen(
        _cadsplat("rig", "watch", "--simulate", "--trigger", "serial", "--rate", "4", "--store", str(store), *SMALL),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        cwd=REPO,
    )
    lines = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if line.startswith("committed"):
            break
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    ids = _committed("".join(lines) + out)
    assert ids and assert_store_sound(store, ids) == sorted(ids)
    assert "triggers" in err.splitlines()[-1]


def test_capture_from_config_with_pattern_cameras(tmp_path):
    (tmp_path / "rig.toml").write_text(
        'rig_id = "bench"\n[[cameras]]\nid = "a"\ndriver = "pattern"\nwidth = 64\nheight = 48\n'
        '[[cameras]]\nid = "b"\ndriver = "pattern"\nwidth = 64\nheight = 48\n[storage]\nroot = "caps"\nmin_free_gb = 0\n'
    )
    r = subprocess.run(
        _cadsplat("rig", "capture", "--config", str(tmp_path / "rig.toml")),
        capture_output=True,
        text=True,
        env=_env(),
        cwd=REPO,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    ids = _committed(r.stdout)
    assert len(ids) == 1 and assert_store_sound(tmp_path / "caps", ids) == ids


def test_bad_input_is_one_sentence_and_nonzero(tmp_path):
    r = subprocess.run(_cadsplat("rig", "capture"), capture_output=True, text=True, env=_env(), cwd=REPO, timeout=60)
    assert r.returncode != 0 and r.stderr.strip() == "Error: give --config rig.toml, or --simulate to run on the synthetic rig"
    (tmp_path / "rig.toml").write_text('[[cameras]]\nid = "a"\ndriver = "pattern"\nwidth = 0\n')
    r = subprocess.run(
        _cadsplat("rig", "capture", "--config", str(tmp_path / "rig.toml")),
        capture_output=True,
        text=True,
        env=_env(),
        cwd=REPO,
        timeout=60,
    )
    assert r.returncode != 0 and "cameras[0].width must be an integer" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_a_second_writer_on_one_store_is_refused_naming_the_first(tmp_path):
    """Two `rig watch` (or a watch and a `rig capture`) on one store: the second is refused in one sentence naming the
    first one's pid, and the first goes on with its own ids, none quarantined."""
    store = tmp_path / "store"
    with watching(store) as first:
        for argv in (("watch", "--simulate", "--rate", "4", "--max-captures", "2"), ("capture", "--simulate")):
            r = subprocess.run(
                _cadsplat("rig", *argv, "--store", str(store), *SMALL),
                capture_output=True,
                text=True,
                env=_env(),
                cwd=REPO,
                timeout=180,
                check=False,
            )
            assert r.returncode != 0 and not _committed(r.stdout), r.stdout
            assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
            assert f"is in use by rig watch (pid {first.pid})" in r.stderr, r.stderr
    code, out, err = first.result
    ids = _committed(out)
    assert code == 0, err
    assert len(ids) == len(set(ids)) >= 1 and assert_store_sound(store, ids) == sorted(ids)
    assert not any((store / "quarantine").iterdir())


def _calibrated_rig(tmp_path: Path) -> Path:
    """rig.toml of two pattern cameras with a board calibration.json beside it and its store in caps/."""
    import numpy as np

    from calibration.calibfile import CalibrationDoc, CalibrationStore
    from calibration.camera import Camera

    k = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    CalibrationStore(tmp_path / "calibration.json").commit(
        CalibrationDoc({c: Camera(k, 64, 48, np.zeros(0), np.eye(4)) for c in "ab"}, source="board")
    )
    (tmp_path / "rig.toml").write_text(
        'rig_id = "bench"\ncalibration = "calibration.json"\n[[cameras]]\nid = "a"\ndriver = "pattern"\nwidth = 64\nheight = 48\n'
        '[[cameras]]\nid = "b"\ndriver = "pattern"\nwidth = 64\nheight = 48\n[storage]\nroot = "caps"\nmin_free_gb = 0\n'
    )
    return tmp_path / "rig.toml"


def test_a_calibration_in_unknown_units_stops_the_rig_at_start_in_one_sentence(tmp_path):
    """`units: "meters"` would make every capture's transforms.json unreadable (all quarantined, frames discarded)."""
    import json

    _calibrated_rig(tmp_path)
    doc = json.loads((tmp_path / "calibration.json").read_text())
    (tmp_path / "calibration.json").write_text(json.dumps({**doc, "units": "meters"}))
    r = subprocess.run(
        _cadsplat("rig", "capture", "--config", str(tmp_path / "rig.toml")),
        capture_output=True,
        text=True,
        env=_env(),
        cwd=REPO,
        timeout=120,
        check=False,
    )
    assert r.returncode != 0 and not _committed(r.stdout) and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert f"{tmp_path / 'calibration.json'}: units 'meters' is not a unit cadsplat knows (one of m, mm, cm, in" in r.stderr
    assert not (tmp_path / "caps" / "captures").exists() or not any((tmp_path / "caps" / "captures").iterdir())


def test_the_kiosk_on_the_store_of_a_running_rig_is_refused_naming_it(tmp_path):
    """The kiosk (`Appliance.from_config`) writes captures into rig.toml's store too: while `rig watch --config` holds it,
    the kiosk is refused naming the rig's pid, before it opens cameras, trigger or store."""
    import pytest

    from calibration.guard import LockHeld
    from deploy.appliance import Appliance
    from rig.store import writer_holds

    config = _calibrated_rig(tmp_path)
    rig = subprocess.Popen(
        _cadsplat("rig", "watch", "--config", str(config)), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=REPO
    )
    try:
        deadline = time.monotonic() + 120
        while not writer_holds(tmp_path / "caps") and rig.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        with pytest.raises(LockHeld, match=rf"in use by rig watch \(pid {rig.pid}\)"):
            Appliance.from_config(config, tmp_path / "library", tmp_path / "work")
        assert rig.poll() is None, rig.communicate()
    finally:
        rig.send_signal(signal.SIGTERM)  # may land before the rig installs its handler: its exit status is not the point here
        rig.communicate(timeout=60)
