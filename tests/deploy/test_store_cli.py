"""`cadsplat store verify | import-spill` and the rig's start importing the spill (in-process, pattern cameras)."""

from __future__ import annotations

import errno

from deploy.cli import main
from tests.deploy.test_faults import _rig_sites, _run_rig, spill_of
from tests.faultfs import FaultyDisk
from tests.rig.conftest import assert_store_sound


def _spilled_store(tmp_path):
    """A store that went read-only mid-capture and stayed so until the rig stopped: (root, spilled ids)."""
    for n in range(1, _rig_sites(tmp_path) + 1):
        root = tmp_path / f"store-{n}"
        outs, _ = _run_rig(root, FaultyDisk(root, fail_at=n, errno_=errno.EROFS, persistent=True))
        ids = [o.capture_id for o in outs if o.status == "spilled"]
        if ids:
            return root, ids
    raise AssertionError("no write site left a capture held")


def test_verify_reports_the_spill_and_import_spill_moves_it_into_the_store(tmp_path, capsys):
    root, ids = _spilled_store(tmp_path)
    spill = str(spill_of(root).root)
    capsys.readouterr()
    assert main(["store", "verify", str(root), "--spill", spill]) == 1
    out = capsys.readouterr().out
    assert f"capture {ids[0]} waits in the spill, not yet in the store (`cadsplat store import-spill {root}`)" in out
    assert f"{len(ids)} waiting in the spill" in out
    assert main(["store", "import-spill", str(root), "--spill", spill]) == 0
    out = capsys.readouterr().out
    assert [line.split()[1] for line in out.splitlines() if line.startswith("imported ")] == ids
    assert main(["store", "verify", str(root), "--spill", spill]) == 0
    assert "0 waiting in the spill; 0 problem(s)" in capsys.readouterr().out
    assert set(ids) <= set(assert_store_sound(root, ids))
    assert main(["store", "import-spill", str(root), "--spill", spill]) == 0  # nothing left: idempotent
    assert "0 capture(s) imported" in capsys.readouterr().out


def test_import_spill_refuses_what_is_not_a_store_in_one_sentence(tmp_path, capsys):
    assert main(["store", "import-spill", str(tmp_path / "nope"), "--spill", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "is not a capture store (no captures/ folder)" in err and err.count("\n") == 1


def test_the_rig_imports_the_spill_when_it_starts(tmp_path, capsys):
    root, ids = _spilled_store(tmp_path)
    capsys.readouterr()
    assert main(["rig", "capture", "--simulate", "--store", str(root), "--spill", str(spill_of(root).root),
                 "--views", "3", "--size", "96", "72", "--min-free-gb", "0"]) == 0
    out = capsys.readouterr().out
    assert [line.split()[1] for line in out.splitlines() if line.startswith("imported ")] == ids
    assert spill_of(root).entries() == [] and set(ids) <= set(assert_store_sound(root, ids))
