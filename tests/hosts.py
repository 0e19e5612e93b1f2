"""Two network hosts on one machine, for tests of what crosses a network (a Ray cluster of two nodes,
torchrun over two nodes): this network namespace and a new one, joined by a veth pair of their own
addresses. Both see the same file system, as the nodes of a cluster on shared storage do. Needs
root and iproute2; :func:`two_hosts` skips the test where either is missing or namespaces are
refused (a container without the capability)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest


@dataclass
class Hosts:
    """The two ends: ``here`` (this namespace) and ``there`` (the namespace ``name``)."""

    name: str
    here_ip: str
    there_ip: str
    here_if: str
    there_if: str
    procs: list[subprocess.Popen] = field(default_factory=list)

    def start(self, cmd: list[str], *, there: bool, env: dict[str, str] | None = None, cwd: Path | None = None,
              log: Path | None = None) -> subprocess.Popen:
        """``cmd`` on one host, in a process group of its own that :meth:`close` ends; its output goes
        to ``log`` (or nowhere)."""
        full = ["ip", "netns", "exec", self.name, *cmd] if there else cmd
        out = open(log, "w") if log else subprocess.DEVNULL  # noqa: SIM115 (the child keeps it)
        proc = subprocess.Popen(full, env={**os.environ, **(env or {})}, cwd=cwd, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        if log:
            out.close()
        self.procs.append(proc)
        return proc

    def kill_tree(self, proc: subprocess.Popen) -> None:
        """SIGKILL ``proc`` and every process descended from it at once, as when their node dies
        (torchrun starts its workers in sessions of their own: killing its group leaves them running)."""
        self.signal_tree(proc, signal.SIGKILL)

    def signal_tree(self, proc: subprocess.Popen, sig: int) -> list[int]:
        """Send ``sig`` to ``proc`` and every process descended from it (SIGSTOP: a node that hangs,
        as a frozen VM does); their process ids."""
        tree = self.tree(proc)
        for pid in tree:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        return tree

    @staticmethod
    def tree(proc: subprocess.Popen) -> list[int]:
        """The process ids of ``proc`` and every process descended from it, ``proc``'s first."""
        children: dict[int, list[int]] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = stat.read_text().rsplit(")", 1)[1].split()
                children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
        tree, todo = [], [proc.pid]
        while todo:
            pid = todo.pop()
            tree.append(pid)
            todo.extend(children.get(pid, []))
        return tree

    def link(self, *, up: bool) -> None:
        """Take the link between the hosts down (packets dropped, no connection closed: a failed
        switch or a node without power, seen from its peer) or bring it up again."""
        _ip("link", "set", self.here_if, "up" if up else "down")

    def close(self) -> None:
        """End every process started here (their whole groups), then the namespace and its veth."""
        for sig, grace in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 10.0)):  # a Ray node drains for 30 s
            for proc in self.procs:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, sig)
            deadline = time.monotonic() + grace
            while any(proc.poll() is None for proc in self.procs) and time.monotonic() < deadline:
                time.sleep(0.1)
        subprocess.run(["ip", "netns", "delete", self.name], capture_output=True)
        subprocess.run(["ip", "link", "delete", self.here_if], capture_output=True)


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    if done.returncode:
        raise OSError(f"ip {' '.join(args)}: {done.stderr.strip()}")


@contextlib.contextmanager
def two_hosts() -> Iterator[Hosts]:
    """A namespace named by this process joined to this one by a veth pair on 10.211.<pid % 250>.0/24
    (.1 here, .2 there); removed with every process :meth:`Hosts.start` made when the block ends."""
    if os.geteuid() != 0 or not shutil.which("ip"):
        pytest.skip("two network hosts need root and iproute2's ip")
    pid = os.getpid()
    net = f"10.211.{pid % 250}"
    hosts = Hosts(f"ssfr-test-{pid}", f"{net}.1", f"{net}.2", f"ssfrh{pid}", f"ssfrt{pid}")
    # a namespace of this name is a killed earlier run's (a process id used again): drop it
    subprocess.run(["ip", "netns", "delete", hosts.name], capture_output=True)
    subprocess.run(["ip", "link", "delete", hosts.here_if], capture_output=True)
    try:
        _ip("netns", "add", hosts.name)
    except OSError as exc:
        pytest.skip(f"network namespaces are refused here ({exc})")
    try:
        _ip("link", "add", hosts.here_if, "type", "veth", "peer", "name", hosts.there_if)
        _ip("link", "set", hosts.there_if, "netns", hosts.name)
        _ip("addr", "add", f"{hosts.here_ip}/24", "dev", hosts.here_if)
        _ip("link", "set", hosts.here_if, "up")
        try:
            for args in (("addr", "add", f"{hosts.there_ip}/24", "dev", hosts.there_if),
                         ("link", "set", hosts.there_if, "up"), ("link", "set", "lo", "up")):
                _ip("netns", "exec", hosts.name, "ip", *args)
        except OSError as exc:  # entering a namespace needs more rights than making one
            pytest.skip(f"processes cannot enter a network namespace here ({exc})")
        yield hosts
    finally:
        hosts.close()
