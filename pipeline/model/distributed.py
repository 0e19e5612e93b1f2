"""Data-parallel training over the processes ``torchrun`` starts (``torch.distributed``).

``torchrun --nproc_per_node N`` sets ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK`` and the rendezvous
address in each process's environment; :func:`start` joins them into one process group (gloo on
the CPU, nccl on CUDA, one GPU per local rank). Without those variables it returns a world of one
process and training runs exactly as before. Small messages (a folder name, the epoch's mean
losses) go through a second gloo group. Every wait has the training group's timeout, however long
rank 0's own work takes: while rank 0 queues for a cache entry's lock or validates an epoch, it
beats once a second (:meth:`World.while_main_works`), so a peer that dies or is cut off is noticed
within the timeout wherever the run is.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import socket
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist

SIOCGIFADDR = 0x8915
"""Linux's ioctl for an interface's (first) IPv4 address."""
STEP_TIMEOUT_S = 300
"""How long (seconds) a process waits for a peer, in forming the group, in a step's all-reduce or for a
heartbeat, before it fails, unless ``DEEP_SSFR_DIST_TIMEOUT`` says otherwise: a peer that died or
cannot be reached ends every node's run within this, rather than torch's 30 minutes."""
BEAT_S = 1.0
"""How often rank 0 tells the waiting ranks it is still there while it works alone."""


@dataclass(frozen=True)
class World:
    """This process's place among the training processes (one process: rank 0 of 1)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that writes checkpoints, metrics, sheets and logs."""
        return self.rank == 0

    def device(self, device: str) -> str:
        """This process's torch device: ``cuda:<local rank>`` for a CUDA run of several, else ``device``."""
        if self.size > 1 and torch.device(device).type == "cuda":
            return f"cuda:{self.local_rank}"
        return device

    @contextlib.contextmanager
    def while_main_works(self, what: str) -> Iterator[None]:
        """Rank 0 runs the block's work (``what``, for messages) while the other ranks wait at its end,
        however long it takes (a cache lock held by another run, validation); the block must not use
        the process group. A thread of rank 0 all-reduces a flag with them every :data:`BEAT_S`
        (0 working, 1 done, -1 failed), so each side fails within the timeout if the other dies or is
        cut off, where a plain barrier would wait for ever on a peer whose connections stay open.
        One process: the block alone."""
        if self.size == 1:
            yield
            return
        if not self.is_main:
            yield
            try:
                while (flag := _beat(0.0)) == 0:
                    pass
            except RuntimeError as exc:
                raise RuntimeError(f"{exc} (waiting while rank 0 was {what})") from exc
            if flag < 0:
                raise RuntimeError(f"rank 0 failed while {what} (its log says why)")
            return
        done, lost = threading.Event(), []
        outcome = [1.0]

        def beat() -> None:
            try:
                every = min(BEAT_S, step_timeout().total_seconds() / 4)  # well inside the others' timeout
                while not done.wait(every):
                    _beat(0.0)
                _beat(outcome[0])
            except RuntimeError as exc:  # a peer gone: the main thread raises it once its work ends
                lost.append(exc)

        beater = threading.Thread(target=beat, name="rank0-beat", daemon=True)
        beater.start()
        try:
            yield
        except BaseException:
            outcome[0] = -1.0
            raise
        finally:
            done.set()
            beater.join()
        if lost:
            raise RuntimeError(f"{lost[0]} (while {what})") from lost[0]

    def share(self, value: Any) -> Any:
        """Rank 0's ``value`` (any picklable object) on every process."""
        if self.size == 1:
            return value
        box = [value]
        dist.broadcast_object_list(box, src=0, group=_wait_group())
        return box[0]

    def mean(self, values: dict[str, float]) -> dict[str, float]:
        """Each value averaged over the processes (every process passes the same keys)."""
        if self.size == 1 or not values:
            return values
        keys = sorted(values)
        total = torch.tensor([values[k] for k in keys], dtype=torch.float64)
        dist.all_reduce(total, group=_wait_group())
        return {k: float(v) / self.size for k, v in zip(keys, total.tolist(), strict=True)}


NETWORK_HINT = ("Where a node's name resolves to another network than the one its peers reach it on, start "
                "each node's torchrun with --local-addr <its address there>, and set GLOO_SOCKET_IFNAME=<its "
                "interface there> (NCCL_SOCKET_IFNAME too on GPUs) if the interface routing to the master is not "
                "it: docs/training_at_scale.md")

PEER_HINT = ("Where a peer process or node ended or cannot be reached (its log says why), run the same command on "
             "every node again once they reach each other: training resumes after the last finished epoch (last.pt)")

_WORLD: World | None = None
_WAIT: Any = None


def step_timeout() -> timedelta:
    """The training group's timeout: ``DEEP_SSFR_DIST_TIMEOUT`` seconds, else :data:`STEP_TIMEOUT_S`."""
    value = os.environ.get("DEEP_SSFR_DIST_TIMEOUT", "").strip()
    try:
        seconds = float(value) if value else STEP_TIMEOUT_S
    except ValueError:
        seconds = -1.0
    if not 0 < seconds < float("inf"):
        raise ValueError(f"DEEP_SSFR_DIST_TIMEOUT must be a positive number of seconds, got {value!r}")
    return timedelta(seconds=seconds)


def _wait_group() -> Any:
    """The gloo group for small messages and heartbeats (created by :func:`start`)."""
    if _WAIT is None:
        raise RuntimeError("distributed training: start() was not called in this process")
    return _WAIT


def _beat(flag: float) -> float:
    """One heartbeat: the sum of every rank's ``flag`` (the waiting ranks give 0)."""
    box = torch.tensor([flag], dtype=torch.float64)
    dist.all_reduce(box, group=_wait_group())
    return float(box.item())


def start(device: str) -> World:
    """Join the processes ``torchrun`` started (once per process; later calls return the same world).

    ``device`` is the run's device kind: ``cuda`` selects nccl and the GPU of this local rank,
    anything else gloo. A world of one process needs no process group and makes none."""
    global _WORLD, _WAIT
    if _WORLD is not None:
        return _WORLD
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        _WORLD = World()
        return _WORLD
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    timeout = step_timeout()
    cuda = torch.device(device).type == "cuda"
    if cuda:
        torch.cuda.set_device(local_rank)
    if "GLOO_SOCKET_IFNAME" not in os.environ and (master := os.environ.get("MASTER_ADDR")):
        # gloo otherwise binds the address this host's name resolves to: Debian's 127.0.1.1, or a
        # network the other nodes cannot reach; the interface that routes to the master reaches them
        if name := reaching_interface(master):
            os.environ["GLOO_SOCKET_IFNAME"] = name
    try:
        if not dist.is_initialized():
            dist.init_process_group("nccl" if cuda else "gloo", timeout=timeout)
            atexit.register(stop)
        _WAIT = dist.new_group(backend="gloo", timeout=timeout)
    except RuntimeError as exc:  # torch's DistError is one
        raise RuntimeError(f"{exc} (rank {rank} of {size}, waited up to {timeout.total_seconds():g} s: "
                           f"DEEP_SSFR_DIST_TIMEOUT). {NETWORK_HINT}") from exc
    _WORLD = World(rank, dist.get_world_size(), local_rank)
    return _WORLD


def reaching_interface(host: str) -> str | None:
    """The name of this machine's network interface whose IPv4 address the route to ``host`` leaves
    from ("lo" for this machine itself); None where that cannot be told (no route, no such
    interface, not Linux)."""
    try:
        import fcntl

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect((host, 9))  # a datagram socket's connect only picks the route: nothing is sent
            local = s.getsockname()[0]
            for _, name in socket.if_nameindex():
                with contextlib.suppress(OSError):  # an interface without an IPv4 address
                    request = struct.pack("256s", name.encode()[:15])
                    if socket.inet_ntoa(fcntl.ioctl(s.fileno(), SIOCGIFADDR, request)[20:24]) == local:
                        return name
    except (ImportError, OSError):
        pass
    return None


def stop() -> None:
    """Leave the process group (at exit; a later :func:`start` joins again)."""
    global _WORLD, _WAIT
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
    _WORLD, _WAIT = None, None
