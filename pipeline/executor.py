"""Where per-frame work runs: in this process (``local``) or sharded over a Ray cluster (``ray``).

With ``ray`` every task runs in a worker process of the cluster named by ``ray_address`` (a local
one on this machine when empty), and writes its files straight into the stage's cache entry, so
every node must see the same ``data_dir`` (shared storage). The driver keeps the entry's lock and
writes its manifest once all tasks are back.

On a GPU every task asks Ray for ``1 / TASKS_PER_GPU`` of one, and Ray gives it its own
(``CUDA_VISIBLE_DEVICES`` set to it, so it is the task's ``cuda:0``); the work is cut into
``TASKS_PER_GPU`` shards per GPU of the cluster instead of one per CPU. A task that asks for none is
given none: it sees every GPU of its node (Ray 2.60; none at all where
``RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO`` is set, as older Ray did by default), so one task per CPU would
crowd onto each node's first GPU while the others idle.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

log = logging.getLogger("deep_ssfr")
T = TypeVar("T")
R = TypeVar("R")

TASKS_PER_GPU = 1
"""Ray tasks sharing one GPU when the run's device is CUDA (each holds 1 / this of it)."""


def _is_cuda(device: str) -> bool:
    return str(device).startswith("cuda")


def shards(items: Sequence[T], count: int) -> list[list[T]]:
    """``items`` cut into at most ``count`` contiguous, nearly equal, non-empty runs (in order)."""
    if not items:
        return []
    count = max(1, min(count, len(items)))
    bounds = [len(items) * k // count for k in range(count + 1)]
    return [list(items[bounds[k]:bounds[k + 1]]) for k in range(count)]


def run_tasks(fn: Callable[[T], R], tasks: Sequence[T], executor: str = "local", address: str = "",
              device: str = "cpu") -> list[R]:
    """``fn(task)`` for every task, results in task order: here one after another (``local``), or
    as Ray tasks (``ray``; ``fn`` and the tasks travel by cloudpickle, so closures over paths,
    configs and networks are fine, open devices and files are not). With a CUDA ``device`` each Ray
    task holds a share of one GPU, which it sees as ``cuda:0``."""
    if executor == "local":
        return [fn(t) for t in tasks]
    if executor != "ray":
        raise ValueError(f"unknown executor {executor!r} (local or ray)")
    try:
        import ray
    except ImportError:
        raise RuntimeError("executor 'ray' needs Ray: pip install 'deep-ssfr[scale]' (or ray)") from None
    address = address or os.environ.get("RAY_ADDRESS", "")
    started = not ray.is_initialized()
    if started:
        ray.init(address=address or None, num_cpus=None if address else os.cpu_count(), include_dashboard=False,
                 configure_logging=False, log_to_driver=False, runtime_env={"env_vars": _worker_env()})
    log.info("ray: %d tasks on %s%s", len(tasks), address or "a local cluster",
             f", {1 / TASKS_PER_GPU:g} GPU each" if _is_cuda(device) else "")
    try:
        remote = ray.remote(num_gpus=1 / TASKS_PER_GPU)(fn) if _is_cuda(device) else ray.remote(fn)
        return ray.get([remote.remote(t) for t in tasks])
    finally:
        if started:
            ray.shutdown()


def cluster_slots(executor: str, device: str = "cpu") -> int:
    """How many tasks to cut the work into: the CPUs of this machine or of the Ray cluster, or on a
    CUDA ``device`` ``TASKS_PER_GPU`` per GPU of the cluster (of this machine before Ray starts)."""
    resource = "GPU" if _is_cuda(device) else "CPU"
    per = TASKS_PER_GPU if resource == "GPU" else 1
    if executor == "ray":
        try:
            import ray

            if ray.is_initialized():
                return max(1, int(ray.cluster_resources().get(resource, 1) * per))
        except ImportError:
            pass
    if resource == "GPU":
        import torch

        return max(1, torch.cuda.device_count() * per)
    return os.cpu_count() or 1


def _worker_env() -> dict[str, Any]:
    """The environment variables a worker needs to behave like this process (device, GL, logs)."""
    keys = ("DEEP_SSFR_DEVICE", "PYOPENGL_PLATFORM", "DEEP_SSFR_LOG", "PYTHONPATH")
    return {k: os.environ[k] for k in keys if k in os.environ}
