"""SIGKILL mid-write: a child process captures and dies at a chosen write (or whenever the parent kills it).

After the kill the store holds only complete, verified captures, every capture the child reported
is there, and the next open moves the half-written one from .incoming/ to quarantine/ with a reason.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from rig.store import CaptureStore
from tests.conftest import REPO
from tests.rig.conftest import assert_store_sound

CHILD = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    import calibration.capture as cc
    import calibration.fileio as fio
    from rig.acquisition import Acquisition, Thresholds, agree_photometry
    from rig.camera import CameraSettings
    from rig.store import CaptureStore
    from rig.synthetic_driver import PatternCamera
    from rig.triggers import SoftwareTrigger

    root, die_at = sys.argv[1], int(sys.argv[2])
    real, n = fio.atomic_write_bytes, [0]
    def write(path, data):
        n[0] += 1
        if n[0] == die_at:
            path = Path(path)  # half of the file in its temp name, as atomic_write_bytes has it, then the power cord
            (path.parent / f".{path.name}.killed.tmp").write_bytes(data[: len(data) // 2])
            os.kill(os.getpid(), signal.SIGKILL)
        return real(path, data)
    cc.atomic_write_bytes = fio.atomic_write_bytes = write
    cams = [PatternCamera(f"cam{i}", index=i, n=4, width=320, height=240) for i in range(4)]
    for c in cams:
        c.open()
    acq = Acquisition(cams, CaptureStore(root, min_free_bytes=0), thresholds=Thresholds(sync_tolerance_ns=10**9),
                      settings=agree_photometry(cams, CameraSettings(320, 240)))
    trig = SoftwareTrigger()
    while True:
        out = acq.handle(trig.fire())
        print(out.status, out.capture_id, flush=True)
    """
)


def _run_child(root, die_at: int, kill_after_s: float | None = None) -> tuple[list[str], int]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(root), str(die_at)], stdout=subprocess.PIPE, text=True, env=env, cwd=REPO)
    if kill_after_s is not None:
        time.sleep(kill_after_s)
        proc.send_signal(signal.SIGKILL)
    out, _ = proc.communicate(timeout=120)
    reported = [line.split()[1] for line in out.splitlines() if line.startswith("committed")]
    return reported, proc.returncode


# 6 writes per capture (store.json counter, 4 images, transforms.json): die in the 3rd capture's
# 2nd image, and in its manifest.
@pytest.mark.parametrize("die_at", [15, 18])
def test_sigkill_mid_write_loses_nothing_reported(store_root, die_at):
    reported, rc = _run_child(store_root, die_at)
    assert rc == -signal.SIGKILL and len(reported) == 2
    assert any((store_root / ".incoming").iterdir())  # the kill did land mid-write
    reopened = CaptureStore(store_root, min_free_bytes=0)
    assert len(reopened.recovered) == 1 and "interrupted write" in reopened.recovered[0].reason
    assert assert_store_sound(store_root, reported) == sorted(reported)
    # the counter survived: the next capture gets a fresh id, above the one that died
    assert int(reopened.reserve_id()[:6]) == 3


def test_sigkill_while_persisting_the_counter(store_root):
    reported, rc = _run_child(store_root, die_at=13)  # the 3rd capture's store.json update
    assert rc == -signal.SIGKILL and len(reported) == 2
    reopened = CaptureStore(store_root, min_free_bytes=0)
    assert reopened.recovered == [] and not list(store_root.glob(".store.json.*"))
    assert assert_store_sound(store_root, reported) == sorted(reported)
    assert int(reopened.reserve_id()[:6]) == 2  # id 2 was never used anywhere


def test_sigkill_from_outside_at_an_arbitrary_moment(store_root):
    reported, rc = _run_child(store_root, die_at=10**9, kill_after_s=2.5)
    assert rc == -signal.SIGKILL
    reopened = CaptureStore(store_root, min_free_bytes=0)
    stored = assert_store_sound(store_root, reported)
    # whatever was in flight is either committed (the kill came after the rename) or quarantined
    assert len(stored) - len(reported) <= 1 and len(reopened.recovered) <= 1
