import os
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="the [cluster] extra (Ray) is not installed")

from deploy.cluster import connect, run_tasks  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    resources = connect(num_cpus=2)
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
