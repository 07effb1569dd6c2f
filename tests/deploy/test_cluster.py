import os
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="the [cluster] extra (Ray) is not installed")

from deploy.cluster import connect, run_tasks  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    try:
        resources = connect(num_cpus=2)
    except Exception as e:  # noqa: BLE001 - whatever stops Ray starting here (no room for its object store, sockets forbidden) skips
        pytest.skip(f"a local Ray cannot start here: {str(e).splitlines()[0] if str(e) else type(e).__name__}")
    yield resources
    ray.shutdown()


def square(x: int) -> dict:
    return {"x": x, "y": x * x, "pid": os.getpid()}


def flaky(marker: str) -> dict:
    # Fails on its first run, succeeds when Ray retries it: a worker hiccup is absorbed.
    p = Path(marker)
    if not p.exists():
        p.write_text("1")
        raise RuntimeError("transient worker failure")
    return {"ok": True}


def always_fails() -> dict:
    raise ValueError("capture has no masks")


def _descendants(root: int) -> list[int]:
    """`root` and every process below it (Ray's GCS, raylet, agents and workers under the driver)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            pid, rest = stat.read_text().split(" (", 1)
            children.setdefault(int(rest.rsplit(") ", 1)[1].split()[1]), []).append(int(pid))
        except (OSError, IndexError, ValueError):
            continue
    out, todo = [], [root]
    while todo:
        out.append(todo.pop())
        todo += children.get(out[-1], [])
    return out


def _listening(pids: list[int]) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket these processes listen on, from /proc/net/tcp{,6}."""
    import socket

    inodes = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").glob("*"):
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[len("socket:[") : -1])
    out = []
    for table, family in (("tcp", socket.AF_INET), ("tcp6", socket.AF_INET6)):
        for row in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            f = row.split()
            if f[3] == "0A" and f[9] in inodes:  # 0A: LISTEN
                ip, port = f[1].split(":")
                raw = bytes.fromhex(ip)
                raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))  # each 32-bit word in host order
                out.append((socket.inet_ntop(family, raw), int(port, 16)))
    return out


def test_a_local_cluster_listens_on_loopback_only(local_ray):
    """Issue 58 (2): GCS, raylet and the driver listened on every interface (`*:port`)."""
    if not Path("/proc/net/tcp").exists():
        pytest.skip("no /proc/net/tcp to read listening sockets from (not Linux)")
    import ipaddress

    gcs_host = ray.get_runtime_context().gcs_address.rsplit(":", 1)[0]
    assert ipaddress.ip_address(gcs_host).is_loopback, gcs_host
    listening = _listening(_descendants(os.getpid()))
    assert listening, "no listening socket found under this process"
    outside = [(a, p) for a, p in listening if not ipaddress.ip_address(a.removeprefix("::ffff:")).is_loopback]
    assert outside == [], f"listening beyond loopback: {outside} of {listening}"


def test_tasks_run_concurrently_on_workers_and_keep_order(local_ray):
    assert local_ray["CPU"] == 2
    seen = []
    out = run_tasks(square, [(f"job{i}", (i,), {}) for i in range(4)], on_result=seen.append)
    assert [r.key for r in out] == ["job0", "job1", "job2", "job3"]
    assert [r.output["y"] for r in out] == [0, 1, 4, 9]
    assert {r.output["pid"] for r in out} != {os.getpid()}
    assert len(seen) == 4


def test_failures_are_retried_then_reported_never_lost(local_ray, tmp_path):
    out = run_tasks(
        lambda key: flaky(str(tmp_path / key)) if key != "bad" else always_fails(),
        [("a", ("a",), {}), ("bad", ("bad",), {}), ("b", ("b",), {})],
        max_retries=2,
    )
    assert [r.status for r in out] == ["done", "failed", "done"]
    assert "capture has no masks" in out[1].error


@pytest.mark.slow
def test_three_captures_on_local_ray_match_single_process(local_ray, tmp_path):
    """Three synthetic captures reconstructed concurrently (preview) equal what one process computes."""
    import json

    import numpy as np

    from calibration.capture import FrameData, read_capture, write_capture
    from deploy.steps import PipelineConfig, process_capture
    from reconstruction.library import build_library

    repo = Path(__file__).resolve().parents[2]
    heldout = read_capture(repo / "sample" / "heldout")
    captures = [repo / "sample" / "train"]
    for k, start in enumerate((1, 2)):
        idx = list(range(start, len(heldout), 4))[:8]
        frames = [
            FrameData(
                Path(heldout.frames[i].file_path).stem,
                (heldout.image(i) * 255).round().astype(np.uint8),
                heldout.camera(i),
                heldout.frames[i].camera_id,
                None,
                heldout.mask(i),
            )
            for i in idx
        ]
        captures.append(write_capture(tmp_path / f"orbit{k}", frames, meta={"rig_id": "sample", "calibration_id": "gt"}).root)
    build_library(repo / "sample" / "library_meshes", tmp_path / "lib", progress=False)
    cfg = PipelineConfig(str(tmp_path / "lib"), "preview", export_formats=("ply",))

    single = process_capture(str(captures[1]), str(tmp_path / "single"), cfg)
    out = run_tasks(process_capture, [(c.name, (str(c), str(tmp_path / "ray" / c.name), cfg), {}) for c in captures])
    assert [r.status for r in out] == ["done"] * 3, [r.error for r in out]
    assert all(r.output["register"]["model_id"] == "medium_clamp_cad" for r in out)

    on_ray = out[1].output
    assert on_ray["reconstruct"]["fit_iou"] == pytest.approx(single["reconstruct"]["fit_iou"], abs=1e-3)
    a = json.loads((tmp_path / "single" / "twin" / "twin.json").read_text())
    b = json.loads((tmp_path / "ray" / captures[1].name / "twin" / "twin.json").read_text())
    np.testing.assert_allclose(np.array(a["sim3_rig_to_object"]["rotation"]), np.array(b["sim3_rig_to_object"]["rotation"]), atol=1e-4)
    np.testing.assert_allclose(a["sim3_rig_to_object"]["translation"], b["sim3_rig_to_object"]["translation"], atol=1e-5)


def test_worker_join_asks_for_token_authentication(monkeypatch):
    """Issue 58 (2): before Ray 2.61 a started head is open unless RAY_AUTH_MODE=token; a joining node insists on it."""
    from deploy.cli import main

    calls = []
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    monkeypatch.setattr("subprocess.call", lambda cmd, env=None: calls.append((cmd, env)) or 0)
    with pytest.raises(SystemExit) as stop:  # `ray start --block`'s exit status is the command's
        main(["worker", "join", "--cluster", "10.0.0.1:6379"])
    assert stop.value.code == 0
    ((cmd, env),) = calls
    assert cmd[1:3] == ["start", "--address=10.0.0.1:6379"] and env["RAY_AUTH_MODE"] == "token"
