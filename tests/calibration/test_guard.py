import os
import subprocess
import sys
import textwrap

import pytest

from calibration.guard import LockHeld, PathOutside, contained, hold_lock


def test_a_second_process_is_refused_naming_the_holder(tmp_path):
    lock = hold_lock(tmp_path, "rig watch")
    code = textwrap.dedent(f"""
        from calibration.guard import LockHeld, hold_lock
        try:
            hold_lock({str(tmp_path)!r}, "service run")
        except LockHeld as e:
            print(e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert f"rig watch (pid {os.getpid()})" in out
    lock.release()
    code_ok = f"from calibration.guard import hold_lock; hold_lock({str(tmp_path)!r}, 'service run'); print('held')"
    assert subprocess.run([sys.executable, "-c", code_ok], capture_output=True, text=True, check=True).stdout.strip() == "held"


def test_a_dead_holder_leaves_no_stale_lock(tmp_path):
    code = f"from calibration.guard import hold_lock; hold_lock({str(tmp_path)!r}, 'rig watch'); import os; os._exit(0)"
    subprocess.run([sys.executable, "-c", code], check=True)
    hold_lock(tmp_path, "rig watch").release()


def test_shared_locks_coexist_but_exclude_a_writer(tmp_path):
    a = hold_lock(tmp_path, "verify", shared=True)
    b = hold_lock(tmp_path, "verify", shared=True)
    with pytest.raises(LockHeld):
        hold_lock(tmp_path, "rig watch")
    a.release()
    b.release()


@pytest.mark.parametrize("bad", ["../x.png", "/etc/passwd", "images/../../x.png"])
def test_paths_outside_the_folder_are_refused(tmp_path, bad):
    with pytest.raises(PathOutside):
        contained(tmp_path / "capture", bad, what="file_path")


def test_a_symlink_out_is_refused_and_an_inside_path_resolves(tmp_path):
    root = tmp_path / "capture"
    (root / "images").mkdir(parents=True)
    (tmp_path / "secret.png").write_bytes(b"x")
    (root / "images" / "link.png").symlink_to(tmp_path / "secret.png")
    with pytest.raises(PathOutside):
        contained(root, "images/link.png")
    assert contained(root, "images/a.png") == (root / "images" / "a.png").resolve()
