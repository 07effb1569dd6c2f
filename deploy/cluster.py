"""Reconstruction on a Ray cluster: one Ray task per capture, asking for a GPU where the cluster has one.

Ray does the scheduling, retries of crashed workers and object transfer; we only decide what one
task is (the same function a single machine runs, so results match) and make sure every job ends
with a result: done with its outputs, or failed with the error after Ray's retries. None is lost.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

# Ray's switch for clusters of several nodes (`ray_constants.ENABLE_RAY_CLUSTERS_ENV_VAR`); off, a node is loopback-only.
_SINGLE_NODE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@dataclass(frozen=True)
class ClusterResult:
    key: str
    status: str  # "done" or "failed"
    output: dict = field(default_factory=dict)
    error: str = ""


def connect(address: str | None = None, *, num_cpus: int | None = None, token: str | None = None) -> dict:
    """Join the Ray cluster at `address` ("auto", "ray://host:10001", "host:6379"), or start a local one.

    A local instance binds loopback only (GCS, raylet, driver and workers): Ray's single-node mode, in
    which the node's address is the loopback one; `_node_ip_address="127.0.0.1"` alone is replaced by
    the machine's outward address and its servers then listen on every interface. Ray's token
    authentication (its default for a local cluster) stays on: a remote cluster's token comes from
    `token`, RAY_AUTH_TOKEN, or Ray's own token file.
    """
    if not address:
        # Read by Ray when it is imported, and by the processes it starts; set on the loaded module too.
        os.environ[_SINGLE_NODE_ENV] = "0"
    import ray
    from ray._private import ray_constants

    if ray.is_initialized():
        return ray.cluster_resources()
    if token:
        os.environ["RAY_AUTH_TOKEN"] = token
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray_constants.ENABLE_RAY_CLUSTER = False
        ray.init(num_cpus=num_cpus, _node_ip_address="127.0.0.1", **kwargs)
    return ray.cluster_resources()


def run_tasks(
    fn: Callable[..., dict],
    jobs: Sequence[tuple[str, tuple, dict]],
    *,
    max_retries: int = 2,
    num_cpus: float = 1,
    use_gpu: bool | None = None,
    on_result: Callable[[ClusterResult], None] | None = None,
) -> list[ClusterResult]:
    """Run `fn(*args, **kwargs)` for each `(key, args, kwargs)` on the connected cluster.

    A task raising an exception or losing its worker is retried `max_retries` times by Ray, then
    reported failed. Results come back in the order given; `on_result` sees them as they finish.
    """
    import ray

    if use_gpu is None:
        use_gpu = ray.cluster_resources().get("GPU", 0) >= 1
    remote = ray.remote(num_cpus=num_cpus, num_gpus=1 if use_gpu else 0, max_retries=max_retries, retry_exceptions=True)(fn)
    refs = {remote.remote(*args, **kwargs): key for key, args, kwargs in jobs}
    results: dict[str, ClusterResult] = {}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        ref = ready[0]
        key = refs[ref]
        try:
            res = ClusterResult(key, "done", ray.get(ref))
        except Exception as e:  # RayTaskError, WorkerCrashedError...: reported, never dropped
            cause = getattr(e, "cause", None) or e
            res = ClusterResult(key, "failed", error=str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__)
        results[key] = res
        if on_result:
            on_result(res)
    return [results[key] for key, _, _ in jobs]
