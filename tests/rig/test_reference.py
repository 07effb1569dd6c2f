"""The empty-rig reference: versioned, verified, taken on command, on schedule and when the belt is empty;
every capture records the version it was taken against."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rig.reference import ReferenceError, ReferenceStore
from rig.triggers import SoftwareTrigger
from tests.rig.conftest import make_acquisition


def test_versions_are_write_once_and_verified(tmp_path):
    refs = ReferenceStore(tmp_path / "references")
    assert refs.current() is None
    img = np.random.default_rng(0).integers(0, 255, (12, 16, 3), dtype=np.uint8)
    a = refs.commit({"cam0": img}, "first")
    b = refs.commit({"cam0": img[::-1].copy()}, "second")
    assert (a.reference_id, b.reference_id) == ("reference-v0001", "reference-v0002")
    assert refs.current().version == 2 and np.array_equal(refs.load(1).frames["cam0"], img)
    (tmp_path / "references" / "v0001" / "cam0.png").write_bytes(b"\x89PNG broken")
    assert refs.verify()[0].endswith("sha256 does not match reference.json (file changed or corrupt)")
    with pytest.raises(ReferenceError):
        refs.load(1)


def test_captures_record_the_reference_and_carry_its_frames(store_root):
    acq = make_acquisition(store_root)
    trig = SoftwareTrigger()
    before = acq.handle(trig.fire())
    ref = acq.take_reference("on command")
    after = acq.handle(trig.fire())
    acq.close()
    assert ref.status == "reference" and ref.capture_id == "reference-v0001"
    assert "background_id" not in acq.store.read(before.capture_id).meta
    cap = acq.store.read(after.capture_id)
    assert cap.meta["background_id"] == "reference-v0001" and set(cap.meta["background"]) == {"cam0", "cam1", "cam2"}
    empty = acq.store.references.current().frames["cam1"]
    assert not (np.asarray(empty) == 230).all(axis=-1).all(axis=0).any()  # the empty belt: no part (the bar)
    # a restarted rig uses the newest reference without being told
    again = make_acquisition(store_root)
    assert again.background_id == "reference-v0001"
    again.close()


def test_the_trigger_saying_the_belt_is_empty_takes_a_reference(store_root):
    acq = make_acquisition(store_root)
    out = acq.handle(SoftwareTrigger().fire({"belt": "empty"}))
    acq.close()
    assert out.status == "reference" and "belt is empty" in out.reason
    assert acq.store.capture_ids() == [] and acq.store.references.versions() == [1]


def test_reference_on_schedule_while_idle(store_root):
    acq = make_acquisition(store_root, reference_every_s=0.05)
    stop = threading.Event()
    seen = []
    source = SoftwareTrigger()

    def on_outcome(o):
        seen.append(o.status)
        if seen.count("reference") >= 2:
            stop.set()

    threading.Timer(10, stop.set).start()
    acq.run(source, stop, on_outcome=on_outcome, poll_s=0.02)
    acq.close()
    assert seen.count("reference") >= 2 and acq.store.references.versions()[:2] == [1, 2]
