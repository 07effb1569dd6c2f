"""`cadsplat store verify | import-spill` and the rig's start importing the spill (in-process, pattern cameras), and both
while a `rig watch` subprocess writes."""

from __future__ import annotations

import errno
import subprocess
import time

from deploy.cli import main
from deploy.commands.store import verify_store
from tests.conftest import REPO
from tests.deploy.test_faults import _rig_sites, _run_rig, spill_of
from tests.deploy.test_rig_cli import SMALL, _cadsplat, _committed, _env, watching
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
    assert (
        main(
            [
                "rig",
                "capture",
                "--simulate",
                "--store",
                str(root),
                "--spill",
                str(spill_of(root).root),
                "--views",
                "3",
                "--size",
                "96",
                "72",
                "--min-free-gb",
                "0",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert [line.split()[1] for line in out.splitlines() if line.startswith("imported ")] == ids
    assert spill_of(root).entries() == [] and set(ids) <= set(assert_store_sound(root, ids))


def test_import_spill_while_the_rig_writes_is_refused_and_quarantines_nothing(tmp_path):
    """A second writer: refused by the store's lock, naming the rig's pid, before it opens the store (which would move the
    rig's capture in flight to quarantine as an interrupted write)."""
    store = tmp_path / "store"
    with watching(store, "--rate", "8", *SMALL) as rig:
        for _ in range(3):
            r = subprocess.run(
                _cadsplat("store", "import-spill", str(store), "--spill", str(tmp_path / "spill")),
                capture_output=True,
                text=True,
                env=_env(),
                cwd=REPO,
                timeout=120,
                check=False,
            )
            assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1, r.stderr
            assert f"is in use by rig watch (pid {rig.pid})" in r.stderr and "imports the spill itself when it starts" in r.stderr
    code, out, err = rig.result
    assert code == 0, err
    assert not any((store / "quarantine").iterdir()) and assert_store_sound(store, _committed(out))


def test_verify_while_the_rig_writes_reports_no_damage_and_leftovers_after_it(tmp_path, capsys):
    """What sits in .incoming/ while the rig holds the store is in flight, not damage (here: a planted entry and the
    rig's own live writes, verified over and over); once the rig has stopped, a leftover is reported."""
    store, spill = tmp_path / "store", str(tmp_path / "spill")
    in_flight = store / ".incoming" / "099999-20260101T000000Z"
    with watching(store, "--rate", "20", "--views", "4", "--size", "320", "240", "--min-free-gb", "0"):
        in_flight.mkdir()
        capsys.readouterr()
        assert main(["store", "verify", str(store), "--spill", spill]) == 0
        assert "being written by the rig; 0 problem(s)" in capsys.readouterr().out
        in_flight.rmdir()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            assert verify_store(store, tmp_path / "spill")[1] == []
        in_flight.mkdir()
    assert main(["store", "verify", str(store), "--spill", spill]) == 1
    assert "1 half-written entries" in capsys.readouterr().out
