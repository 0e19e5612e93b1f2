"""Scale-out past one machine, on two network hosts of this machine (``tests/hosts.py``): a Ray
cluster of two nodes (the head here with one CPU, a second node in a network namespace of its own
with two, started in another folder) and torchrun over the same two hosts, each the way
docs/scaling.md and docs/training_at_scale.md tell a user to start them. The hosts share the file
system, as a cluster's nodes share storage."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from stages import cli
from tests.conftest import ROOT
from tests.hosts import Hosts, two_hosts

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
RAY_START = [str(BIN / "ray"), "start", "--block", "--disable-usage-stats"]
ENV = {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "RAY_USAGE_STATS_ENABLED": "0", "DEEP_SSFR_DEVICE": "cpu"}
KEEPALIVE = {"RAY_grpc_client_keepalive_time_ms": "10000"}
"""The cluster's nodes and drivers ping every 10 s, so that its nodes accept a driver's pings that
often (the product's 60 s, ``executor.RAY_KEEPALIVE``, is the most often that nodes started with
Ray's defaults accept); the answer's wait stays Ray's 120 s, so that a cut link does not end them."""


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _wait_for_port(host: str, port: int, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s, contextlib.suppress(OSError):
            s.settimeout(0.5)
            s.connect((host, port))
            return
        time.sleep(0.2)
    raise TimeoutError(f"{what} did not listen on {host}:{port} within {timeout:.0f} s")


@dataclass
class Cluster:
    """A running Ray cluster of the two hosts, and how a driver joins it."""

    hosts: Hosts
    address: str
    env: dict[str, str]
    """What a driver of this cluster needs in its environment (the nodes' token, the address)."""
    folder: Path
    node: subprocess.Popen | None = None
    """The second node's ``ray start --block``, in the namespace."""
    starts: int = 0

    def start_node(self) -> None:
        """``ray start --address`` on the second host (2 CPUs, a folder and Ray temp folder of its own
        each time: a killed node's stay behind), and wait until the cluster counts two live nodes, this
        one among them: a killed node counts as live until Ray's health checks find it dead, so a count
        of two alone can be the head and the old node, before this one has joined."""
        self.starts += 1
        name = f"node{self.starts}"
        (self.folder / f"{name}_cwd").mkdir()
        self.node = self.hosts.start(
            [*RAY_START, "--address", self.address, "--node-ip-address", self.hosts.there_ip, "--num-cpus", "2",
             "--temp-dir", str(self.folder / name)], there=True, env=self.env, cwd=self.folder / f"{name}_cwd",
            log=self.folder / f"{name}.log")
        joined = self.drive(f"""if True:
            import json, time, ray
            ray.init(configure_logging=False, log_to_driver=False)
            def joined():  # this node (its raylet's socket lies in its own temp folder) and the head alone
                alive = [n for n in ray.nodes() if n["Alive"]]
                return len(alive) == 2 and any(n["RayletSocketName"].startswith({str(self.folder / name)!r})
                                               for n in alive)
            deadline = time.monotonic() + 90  # a killed node before it is found dead: Ray's health checks
            while not joined() and time.monotonic() < deadline:
                time.sleep(0.2)
            print(json.dumps(joined()))""")
        assert joined is True, (self.folder / f"{name}.log").read_text()[-2000:]

    def drive(self, code: str) -> object:
        """Run ``code`` as a driver program here (a fresh process, as a user's would be) and return what
        it printed last, read as JSON."""
        done = subprocess.run([sys.executable, "-c", code], env={**os.environ, **self.env}, cwd=ROOT,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def hosts():
    with two_hosts() as h:
        yield h


@pytest.fixture
def cluster(ray_cluster):
    """The module's cluster, its second node started again if it has ended (Ray drops a node cut off
    for longer than its health checks allow, as the cut-off training test's link can be)."""
    if ray_cluster.node is not None and ray_cluster.node.poll() is not None:
        ray_cluster.start_node()
    return ray_cluster


@pytest.fixture(scope="module")
def ray_cluster(hosts):
    """``ray start --head`` here (1 CPU) and ``ray start --address`` there (2 CPUs), each blocking in
    its own process group and folder, with a Ray temp folder of its own (short: Ray's sockets live
    there). Ray 2.60 turns token authentication on for a cluster wherever ``~/.ray/auth_token``
    exists (a local ``ray.init`` writes one) and a driver joining by address sends a token only
    under ``RAY_AUTH_MODE=token``, read when Ray is imported: the nodes and every driver here share
    a token of their own (docs/scaling.md), and the drivers are processes of their own. All ping their
    connections every 10 s (:data:`KEEPALIVE`)."""
    pytest.importorskip("ray")
    folder = Path(tempfile.mkdtemp(prefix="ssfr-ray-", dir="/tmp"))
    port = _free_port(hosts.here_ip)
    address = f"{hosts.here_ip}:{port}"
    env = {**ENV, **KEEPALIVE, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    (folder / "head_cwd").mkdir()
    hosts.start([*RAY_START, "--head", "--node-ip-address", hosts.here_ip, "--port", str(port), "--num-cpus", "1",
                 "--temp-dir", str(folder / "head"), "--include-dashboard", "false"], there=False, env=env,
                cwd=folder / "head_cwd", log=folder / "head.log")
    _wait_for_port(hosts.here_ip, port, 60, "the Ray head")
    cluster = Cluster(hosts, address, {**env, "RAY_ADDRESS": address}, folder)
    cluster.start_node()
    yield cluster
    hosts.close()  # the nodes end before their folders go
    shutil.rmtree(folder, ignore_errors=True)


SHARDS = """if True:
    import json, os, time
    import ray
    from pipeline.executor import cluster_slots, connected, run_sharded

    def where(shard):
        time.sleep(0.5)  # long enough that the three tasks run at once, one a CPU
        return ray.util.get_node_ip_address(), shard, os.getcwd(), os.environ.get("DEEP_SSFR_EXR_THREADS")

    os.environ["DEEP_SSFR_EXR_THREADS"] = "1"  # the driver's settings travel; the nodes have none
    done = run_sharded(where, 6, "ray", os.environ["RAY_ADDRESS"])
    left = ray.is_initialized()
    with connected("ray"):  # joined once, counted from inside too
        slots = cluster_slots("ray", "cpu")
    print(json.dumps({"done": done, "left_connected": left, "slots": slots, "cwd": os.getcwd()}))"""


def test_work_is_cut_per_cpu_of_the_cluster_and_runs_on_both_nodes(cluster):
    """Three CPUs over two nodes give three shards, not this machine's core count, and the tasks run
    on both hosts, the second in its own folder (nothing a task does may lean on the driver's), with
    the driver's DEEP_SSFR_ settings."""
    out = cluster.drive(SHARDS)
    assert [shard for _, shard, _, _ in out["done"]] == [[0, 1], [2, 3], [4, 5]]
    assert {ip for ip, _, _, _ in out["done"]} == {cluster.hosts.here_ip, cluster.hosts.there_ip}
    assert any(cwd != out["cwd"] for _, _, cwd, _ in out["done"])
    assert [threads for *_, threads in out["done"]] == ["1"] * 3
    assert out["slots"] == 3 and not out["left_connected"], "the block that joined leaves"


def test_a_gpu_run_on_a_cluster_without_gpus_is_an_error_not_a_hang(cluster):
    message = cluster.drive("""if True:
        import json
        from pipeline.executor import run_sharded
        try:
            run_sharded(print, 2, "ray", device="cuda")
        except RuntimeError as exc:
            print(json.dumps(str(exc)))""")
    assert "has no GPU" in message


def test_dataset_and_a_users_sequence_over_two_nodes_equal_serial_runs(cluster, tiny_dam, tmp_path):
    """The dataset and evaluate stages and ``render PATTERN`` (relative paths, from a folder the
    second node does not start in) sharded over the two nodes write what serial runs write, byte for
    byte, into the same cache entries (the evaluation's metrics but for their timings)."""
    from tests.test_cli import _drop
    from tests.test_executor import evaluation_metrics

    body = yaml.safe_load(tiny_dam.read_text())
    body["dataset"] = {"width": 48, "height": 48, "frame_stride": 1, "holdout_scenes": ["tiny_dam"]}
    body["evaluate"] = {"methods": ["bilateral", "nrf"], "frames_per_sequence": 2}
    tiny_dam.write_text(yaml.safe_dump(body))
    serial = tiny_dam.parent / "data"
    body.update(data_dir=str(tmp_path / "ray_data"), scene_dir=str(tiny_dam.parent / "scenes"),
                executor="ray", ray_address=cluster.address)
    (tmp_path / "ray.yaml").write_text(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", str(tiny_dam)]) == 0
    sharded = _command(cluster, ["dataset", "--config", str(tmp_path / "ray.yaml")], ROOT)
    assert f"ray: 3 tasks on {cluster.address} (2 nodes, 3 CPUs)" in sharded
    _same_exrs(serial / "dataset", tmp_path / "ray_data" / "dataset", 12)
    assert cli.main(["evaluate", "--config", str(tiny_dam)]) == 0
    assert "ray: 2 tasks" in _command(cluster, ["evaluate", "--config", str(tmp_path / "ray.yaml")], ROOT)
    assert evaluation_metrics(serial) == evaluation_metrics(tmp_path / "ray_data")

    users = tmp_path / "users"
    users.mkdir()
    _drop(users, frames=range(1, 7))
    args = ["render", "drop_{}.ply", "--radius", "0.01", "--size", "48x48", "--method", "nrf"]
    _command(cluster, [*args, "--out", "serial"], users, executor=False)
    sharded = _command(cluster, [*args, "--out", "sharded", "--executor", "ray"], users)  # RAY_ADDRESS
    assert f"ray: 3 tasks on {cluster.address} (2 nodes, 3 CPUs)" in sharded
    written = sorted(p.name for p in (users / "serial").glob("frame_*.exr"))
    assert written == [f"frame_{i:04d}.exr" for i in range(1, 7)]
    for name in written:
        assert (users / "sharded" / name).read_bytes() == (users / "serial" / name).read_bytes(), name


def _command(cluster: Cluster, argv: list[str], cwd: Path, executor: bool = True) -> str:
    """``deep-ssfr ARGV`` run from ``cwd`` as the cluster's driver (or with no cluster); its log."""
    env = {**os.environ, **(cluster.env if executor else ENV)}
    done = subprocess.run([str(BIN / "deep-ssfr"), *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stderr


def _same_exrs(a_root: Path, b_root: Path, count: int) -> None:
    (a,) = a_root.iterdir()
    (b,) = b_root.iterdir()
    assert a.name == b.name, "the executor is not part of the key: both runs fill the same entry"
    files = sorted(p.relative_to(a) for p in a.rglob("*.exr"))
    assert len(files) == count and files == sorted(p.relative_to(b) for p in b.rglob("*.exr"))
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_torchrun_over_two_hosts_trains_what_two_processes_on_one_train(hosts, straight, tmp_path, monkeypatch):
    """``make train-ddp`` with the multi-node TORCHRUN_ARGS of docs/training_at_scale.md, one process
    a host, gives the checkpoint that two processes on one host give, bit for bit (the ranks, not the
    hosts, split the batches), and rank 0 alone writes it."""
    import torch

    from pipeline.model.inference import load_refiner

    monkeypatch.delenv("GLOO_SOCKET_IFNAME", raising=False)  # the nodes choose their own
    two = _copy_of(straight, tmp_path, "two")
    for code, log in _train_on_two_hosts(hosts, two, tmp_path):
        assert code == 0, log[-3000:]
    (a,) = (straight.parent / "data" / "train").glob("*/last.pt")
    (b,) = (tmp_path / "two" / "data" / "train").glob("*/last.pt")
    assert a.parent.name == b.parent.name
    one, two_hosts_state = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
    assert [h["processes"] for h in two_hosts_state["history"]] == [2, 2, 2, 2]
    for k, v in one["generator"].items():
        assert torch.equal(v, two_hosts_state["generator"][k]), k
    assert load_refiner(b.parent / "best.pt").splat == "ellipsoid"
    assert not list((tmp_path / "two" / "data").rglob("*.tmp-*"))


def test_a_node_whose_peer_never_joins_ends_within_the_timeout_not_torchs_30_minutes(hosts, tmp_path):
    """The second node cannot read the config (the shared storage not mounted there: its path is
    missing on it) and ends before it joins; the first, whose rendezvous had both, waits for it in
    forming the group and ends within ``DEEP_SSFR_DIST_TIMEOUT`` (torch's own is 30 minutes) with
    the stage's one line, which names its rank, the wait and what to set."""
    from tests.test_model import _tiny_train_config

    config = _tiny_train_config(tmp_path, "cut")
    subprocess.run([sys.executable, "-m", "stages.cli", "dataset", "--config", config], cwd=ROOT, check=True,
                   env={**os.environ, **ENV}, capture_output=True)
    began = time.monotonic()
    wait = {"DEEP_SSFR_DIST_TIMEOUT": "15"}
    (here, here_log), (there, there_log) = _train_on_two_hosts(hosts, config, tmp_path, wait, wait,
                                                               there_config="missing/config.yaml")
    took = time.monotonic() - began
    assert there != 0 and "config.yaml" in there_log, there_log[-3000:]
    assert here != 0 and "train: error:" in here_log, here_log[-3000:]
    assert "of 2, waited up to 15 s: DEEP_SSFR_DIST_TIMEOUT). " in here_log and "--local-addr" in here_log
    assert took < 90, f"{took:.0f} s"
    assert not list((tmp_path / "cut" / "data" / "train").glob("*/manifest.json"))


def test_a_node_killed_mid_training_ends_the_other_and_both_resume_to_a_straight_runs_weights(hosts, straight,
                                                                                            tmp_path):
    """The second node's torchrun and worker SIGKILLed after an epoch: the first node's run ends with
    the stage's error instead of waiting, and the same two commands again resume from the last
    checkpoint to the weights a straight two-process run trains, bit for bit."""
    cut = _copy_of(straight, tmp_path, "cut")
    wait = {"DEEP_SSFR_DIST_TIMEOUT": "60"}
    procs, logs = _start_on_two_hosts(hosts, cut, tmp_path, wait, wait)
    _wait_for_an_epoch(procs, tmp_path / "cut")
    hosts.kill_tree(procs[1])  # the node's torchrun and its worker at once, as when the node dies
    procs[1].wait()
    began = time.monotonic()
    code = procs[0].wait(timeout=120)
    log = logs[0].read_text()
    assert code != 0 and "train: error:" in log and "(rank 0 of 2). Where a peer process or node" in log, log[-3000:]
    assert time.monotonic() - began < 50, "the survivor noticed the closed connection, not the timeout"
    _resumes_to_the_straight_run(hosts, tmp_path, straight, cut)


def test_nodes_cut_off_mid_training_end_within_the_timeout_and_resume_once_joined_again(hosts, straight, tmp_path):
    """The link between the nodes goes down after an epoch: packets are dropped and no connection is
    closed, as when a switch fails or a node loses power. Each node's run ends with the stage's error
    once ``DEEP_SSFR_DIST_TIMEOUT`` has passed (torch's own is 30 minutes, gloo's socket waits have
    none), and with the link back the same two commands resume to a straight run's weights."""
    cut = _copy_of(straight, tmp_path, "cut")
    wait = {"DEEP_SSFR_DIST_TIMEOUT": "15"}
    procs, logs = _start_on_two_hosts(hosts, cut, tmp_path, wait, wait)
    _wait_for_an_epoch(procs, tmp_path / "cut")
    hosts.link(up=False)
    began = time.monotonic()
    try:
        code = procs[0].wait(timeout=90)
        took = time.monotonic() - began
    finally:
        hosts.link(up=True)
    log = logs[0].read_text()
    assert code != 0 and "train: error:" in log and "(rank 0 of 2). Where a peer process or node" in log, log[-3000:]
    assert took < 15 + 30, f"{took:.0f} s"
    code, log = procs[1].wait(timeout=120), logs[1].read_text()
    assert code != 0 and "train: error:" in log and "(rank 1 of 2). Where a peer process" in log, log[-3000:]
    _resumes_to_the_straight_run(hosts, tmp_path, straight, cut)


@pytest.fixture(scope="module")
def straight(tmp_path_factory) -> Path:
    """A config of four epochs (about a second each) with its dataset and the weights two processes
    on one host train from it: what every multi-node training run here must give, bit for bit."""
    from tests.test_model import _tiny_train_config

    folder = tmp_path_factory.mktemp("straight")
    path = Path(_tiny_train_config(folder, "straight"))
    body = yaml.safe_load(path.read_text())
    body["train"].update(epochs=4, crops_per_frame=24)  # about a second an epoch: the fault lands between
    path.write_text(yaml.safe_dump(body))
    subprocess.run([sys.executable, "-m", "stages.cli", "dataset", "--config", str(path)], cwd=ROOT, check=True,
                   env={**os.environ, **ENV}, capture_output=True)
    one_host = [str(BIN / "torchrun"), "--standalone", "--nproc_per_node", "2", "-m", "stages.cli", "train", "--config"]
    assert subprocess.run([*one_host, str(path)], cwd=ROOT, env={**os.environ, **ENV},
                          capture_output=True).returncode == 0
    return path


def _copy_of(straight: Path, tmp_path: Path, name: str) -> str:
    """The straight config and its simulation and dataset (not its training) under ``tmp_path/name``."""
    body = yaml.safe_load(straight.read_text())
    body["data_dir"] = str(tmp_path / name / "data")
    (tmp_path / name).mkdir()
    path = tmp_path / name / straight.name
    path.write_text(yaml.safe_dump(body))
    for stage in ("simulate", "dataset"):
        shutil.copytree(straight.parent / "data" / stage, tmp_path / name / "data" / stage)
    return str(path)


def _wait_for_an_epoch(procs: list[subprocess.Popen], root: Path) -> None:
    """Until the run under ``root`` has logged its first epoch (or a node has ended)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and all(p.poll() is None for p in procs):
        if any(len(m.read_text().splitlines()) >= 1 for m in (root / "data" / "train").glob("*/metrics.jsonl")):
            return
        time.sleep(0.05)


def _resumes_to_the_straight_run(hosts: Hosts, tmp_path: Path, straight: Path, cut: str) -> None:
    """The broken run left an unfinished entry after a whole epoch; the same two commands again
    resume it to the straight run's weights, bit for bit."""
    import torch

    (entry,) = (tmp_path / "cut" / "data" / "train").iterdir()
    done = torch.load(entry / "last.pt", weights_only=True)["epoch"]
    assert 1 <= done < 4 and not (entry / "manifest.json").exists(), done
    for code, log in _train_on_two_hosts(hosts, cut, tmp_path):
        assert code == 0, log[-3000:]
    (a,) = (straight.parent / "data" / "train").glob("*/last.pt")
    one, resumed = torch.load(a, weights_only=True), torch.load(entry / "last.pt", weights_only=True)
    assert resumed["epoch"] == 4 and [h["epoch"] for h in resumed["history"]] == [1, 2, 3, 4]
    for k, v in one["generator"].items():
        assert torch.equal(v, resumed["generator"][k]), k


def _train_on_two_hosts(hosts: Hosts, config: str, tmp_path: Path, env_here: dict[str, str] | None = None,
                        env_there: dict[str, str] | None = None,
                        there_config: str | None = None) -> list[tuple[int, str]]:
    """``torchrun -m stages.cli train`` over the two hosts (:func:`_start_on_two_hosts`) to its end; each
    node's exit code and log."""
    procs, logs = _start_on_two_hosts(hosts, config, tmp_path, env_here, env_there, there_config)
    return [(proc.wait(timeout=240), log.read_text()) for proc, log in zip(procs, logs, strict=True)]


def _start_on_two_hosts(hosts: Hosts, config: str, tmp_path: Path, env_here: dict[str, str] | None = None,
                        env_there: dict[str, str] | None = None,
                        there_config: str | None = None) -> tuple[list[subprocess.Popen], list[Path]]:
    """``torchrun -m stages.cli train`` started on the two hosts, one process each, from different folders
    (``there_config``: the second node's config path, if another); the nodes and their logs. Each
    host's name resolves to another network here (as on a node with several, or Debian's
    127.0.1.1): each node names its address on the cluster's network, and the endpoint's node,
    given by address rather than name, is told it keeps the store. No GLOO_SOCKET_IFNAME: gloo
    binds the interface that routes to the master (``distributed.reaching_interface``)."""
    port = _free_port(hosts.here_ip)
    node = [str(BIN / "torchrun"), "--nnodes", "2", "--nproc_per_node", "1", "--rdzv-backend", "c10d",
            "--rdzv-endpoint", f"{hosts.here_ip}:{port}", "--rdzv-id", f"ssfr-{port}"]
    train = ["-m", "stages.cli", "train", "--config", config]
    there_train = ["-m", "stages.cli", "train", "--config", there_config or config]
    logs = [tmp_path / f"node0-{port}.log", tmp_path / f"node1-{port}.log"]
    procs = [hosts.start([*node, "--local-addr", hosts.here_ip, "--rdzv-conf", "is_host=1", *train], there=False,
                         env={**ENV, **(env_here or {})}, cwd=ROOT, log=logs[0]),
             hosts.start([*node, "--local-addr", hosts.there_ip, *there_train], there=True,
                         env={**ENV, **(env_there or {})}, cwd=tmp_path, log=logs[1])]
    return procs, logs


def test_the_interface_to_a_host_is_the_one_its_route_leaves_from(hosts):
    from pipeline.model.distributed import reaching_interface

    assert reaching_interface(hosts.there_ip) == hosts.here_if
    assert reaching_interface("127.0.0.1") == "lo"
    assert reaching_interface("name.invalid") is None


def test_a_killed_driver_of_a_cluster_run_resumes_to_a_serial_runs_bytes(cluster, tiny_dam, tmp_path):
    """The dataset command SIGKILLed while its tasks write on both nodes: the entry stays
    unfinished, the tasks of the dead driver's job end, and each task's journal records what it
    finished, so a re-run redoes a file damaged since and resumes to what a serial run writes,
    with no temporary file or journal left."""
    import signal

    serial, sharded, views = _sixty_views(cluster, tiny_dam, tmp_path)
    proc = subprocess.Popen([str(BIN / "deep-ssfr"), "dataset", "--config", str(sharded)], cwd=ROOT,
                            env={**os.environ, **cluster.env}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_for_views(views, 6, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    (entry,) = views.iterdir()
    assert not (entry / "manifest.json").exists(), "the kill must land while the tasks write"
    written = len(list(entry.glob("*/frame_*.exr")))
    assert 6 <= written < 60, written
    records = [json.loads(line) for j in entry.glob("journal-*.jsonl") for line in j.read_text().splitlines()
               if line.endswith("}")]  # a line the kill cut short is skipped, as the resume does
    assert records, "the tasks journal their views in journals of their own (the driver wrote none)"
    assert {r["file"] for r in records} <= {str(p.relative_to(entry)) for p in entry.glob("*/frame_*.exr")}
    damaged = entry / records[0]["file"]
    damaged.write_bytes(damaged.read_bytes()[:200])  # a task's finished view, damaged after the kill
    log = _command(cluster, ["dataset", "--config", str(sharded)], ROOT)
    assert "ray: 3 tasks" in log and f"{records[0]['file']} is damaged (200 bytes" in log, log[-2000:]
    _same_exrs(serial, views, 60)
    assert not list(views.parent.rglob("*.tmp-*")) and not list(views.rglob("journal*.jsonl"))


def test_a_node_killed_while_its_tasks_write_leaves_them_to_the_other_node(cluster, tiny_dam, tmp_path):
    """The second node SIGKILLed (its raylet and the workers writing two of the three shards) in a
    dataset run over the cluster: Ray runs the dead node's tasks again on the head, and the one
    command ends with a serial run's bytes, leaving none of the dead tasks' temporary files or
    journals behind. The node then joins again, as a restarted node would."""
    serial, sharded, views = _sixty_views(cluster, tiny_dam, tmp_path)
    log = tmp_path / "driver.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([str(BIN / "deep-ssfr"), "dataset", "--config", str(sharded)], cwd=ROOT,
                                env={**os.environ, **cluster.env}, stdout=out, stderr=subprocess.STDOUT)
    try:
        _wait_for_views(views, 6, proc)
        (entry,) = views.iterdir()
        assert cluster.node is not None
        cluster.hosts.kill_tree(cluster.node)
        written = len(list(entry.glob("*/frame_*.exr")))
        assert written < 40, f"{written} views: a task of the node's must still be writing when it dies"
        code = proc.wait(timeout=240)
    finally:
        _restart_node(cluster, proc)
    assert code == 0, log.read_text()[-3000:]
    assert "ray: 3 tasks" in log.read_text()
    _same_exrs(serial, views, 60)
    assert not list(views.parent.rglob("*.tmp-*")) and not list(views.rglob("journal*.jsonl"))


def _restart_node(cluster: Cluster, proc: subprocess.Popen) -> None:
    """End the run ``proc`` (ended already, unless an assertion failed) and the second node, then
    start the node again for the tests after this one."""
    proc.kill()
    assert cluster.node is not None
    cluster.hosts.kill_tree(cluster.node)
    cluster.node.wait()
    cluster.start_node()


def _sixty_views(cluster: Cluster, tiny_dam: Path, tmp_path: Path) -> tuple[Path, Path, Path]:
    """The dataset of 30 frames (60 views at 48 x 48) built serially from ``tiny_dam``, and a config
    of the same work sharded over the cluster into a cache of its own, its frames simulated there
    (one Ray task, asking for 2 CPUs): the serial dataset's folder, the sharded config and the
    sharded dataset's folder."""
    body = yaml.safe_load(tiny_dam.read_text())
    body["simulate"]["frames"] = 30
    body["dataset"] = {"width": 48, "height": 48, "frame_stride": 1, "holdout_scenes": ["tiny_dam"]}
    tiny_dam.write_text(yaml.safe_dump(body))
    sharded = tmp_path / "sharded" / "config.yaml"
    sharded.parent.mkdir()
    body.update(data_dir=str(sharded.parent / "data"), scene_dir=str(tiny_dam.parent / "scenes"), executor="ray",
                ray_address=cluster.address)
    sharded.write_text(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", str(tiny_dam)]) == 0
    simulated = _command(cluster, ["simulate", "--config", str(sharded)], ROOT)
    assert f"ray: 1 tasks on {cluster.address} (2 nodes, 3 CPUs, 2 a task)" in simulated  # the driver's 2 cores
    return tiny_dam.parent / "data" / "dataset", sharded, sharded.parent / "data" / "dataset"


def _wait_for_views(views: Path, count: int, proc: subprocess.Popen) -> None:
    """Until ``count`` views are written under ``views`` (or the run has ended)."""
    _wait_until(lambda: len(list(views.glob("*/*/frame_*.exr"))) >= count, proc)


def _wait_until(done: Callable[[], bool], proc: subprocess.Popen, poll: float = 0.02) -> None:
    """Until ``done()`` (or the run ``proc`` has ended, or two minutes have passed)."""
    deadline = time.monotonic() + 120
    while not done() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(poll)


def test_a_frozen_nodes_workers_write_nothing_once_the_run_has_finished(cluster, tiny_dam, tmp_path):
    """The second node frozen (SIGSTOP of its raylet and workers: a hung machine, or one cut off with
    its storage still mounted, where no connection closes) once both its tasks have written and while
    one of them, at least, is writing: the driver's keepalive (here 10 s and 5 s;
    ``executor.RAY_KEEPALIVE`` by default, not Ray's 7 minutes) finds their connections dead, Ray
    runs the unfinished tasks again on the head (backup copies off: they would race the retries
    there), and the command ends whole. The node's workers,
    thawed once the run has finished and their raylet still frozen, go on with their views, and the
    finished entry gets none of their writes: no file rewritten, no journal, no temporary."""
    _, changed, thawed_ran, log, _ = _freeze_the_node_mid_run(
        cluster, tiny_dam, tmp_path, {"RAY_grpc_client_keepalive_timeout_ms": "5000",
                                      "DEEP_SSFR_RAY_BACKUP_FACTOR": "0"})
    assert "backup cop" not in log
    assert thawed_ran, "the thawed workers ran"
    assert not changed, changed


def test_a_hung_nodes_tasks_are_overtaken_by_backup_copies_on_the_head(cluster, tiny_dam, tmp_path):
    """The second node frozen as above, but with the default backup copies and Ray's own 120 s wait
    for a ping's answer, so that no keepalive finds the node's connections dead for over two
    minutes: once its tasks (both, or the one still running when it froze) have run twice as long
    as the head's (and 10 s), backup copies of them run on the head's free CPU, the command ends
    with a serial run's bytes, its cancels of the hung tries holding it up 10 s at most (they never
    end), and the node's workers, thawed once it has finished, write nothing into the entry. (About
    20 s after the freeze here; with copies off the same run ended 150 s after its start, once Ray
    found the node dead.)"""
    took, changed, _, log, hung = _freeze_the_node_mid_run(cluster, tiny_dam, tmp_path,
                                                           {"RAY_grpc_client_keepalive_timeout_ms": "120000"})
    # one of the node's two tasks may have ended before the freeze; one that had written its last view
    # but not yet returned is frozen too, and gets a copy as well
    started = log.count("a backup copy started")
    copies = "copy" if started == 1 else "copies"
    assert hung <= started <= 2 and f"ray: {started} backup {copies}, {started} of them finished first" in log, (
        hung, log[-3000:])
    assert f"ray: {started} cancelled {copies} did not end within 10 s (on a hung node?)" in log, log[-3000:]
    assert not changed, changed
    print(f"the run ended {took:.0f} s after the freeze")


def _freeze_the_node_mid_run(cluster: Cluster, tiny_dam: Path, tmp_path: Path,
                             env: dict[str, str]) -> tuple[float, list, bool, str, int]:
    """A dataset run of 60 views over the cluster (its driver's environment ``env`` added), the
    second node frozen once both its tasks have written a view and while one of them, at least, is
    writing, its workers thawed (their raylet still frozen) once the run has ended and given 5 s:
    the seconds from the freeze to the run's end, the entry's files and folders changed after it
    ended (times and inodes), whether the thawed workers ran, the driver's log, and how many of the
    node's tasks were still writing when it froze (one or both). The serial run's bytes are checked."""
    import signal

    serial, sharded, views = _sixty_views(cluster, tiny_dam, tmp_path)
    log = tmp_path / "driver.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([str(BIN / "deep-ssfr"), "dataset", "--config", str(sharded)], cwd=ROOT,
                                env={**os.environ, **cluster.env, **env}, stdout=out, stderr=subprocess.STDOUT)
    assert cluster.node is not None
    try:
        node = cluster.node
        _wait_until(lambda: len({pid for pid, n in _writers(views).items() if n} & set(cluster.hosts.tree(node)))
                    >= 2, proc, poll=0.05)  # until both of the node's tasks have written a view
        frozen = cluster.hosts.signal_tree(node, signal.SIGSTOP)
        start = time.monotonic()
        views_of = {pid: n for pid, n in _writers(views).items() if pid in frozen}
        # one of the two may have finished its 20 views already: its worker can start seconds before the
        # other's (found in a fresh-clone CI run: 20 and 3 views); the other is then still writing
        writing = [pid for pid, n in views_of.items() if n < 20]
        assert len(views_of) == 2 and all(views_of.values()) and writing, (
            f"{views_of} of {_writers(views)}: the node's two tasks must have written and one must still be "
            f"writing (the run: {proc.poll()})\n" + log.read_text()[-3000:])
        (entry,) = views.iterdir()
        code = proc.wait(timeout=240)
        took = time.monotonic() - start
        assert code == 0, log.read_text()[-3000:]
        finished = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in entry.rglob("*")}
        ticks = {pid: _cpu_ticks(pid) for pid in writing}
        for pid in views_of:  # their raylet stays frozen, so nothing tells them that their node is gone
            os.kill(pid, signal.SIGCONT)
        time.sleep(5)
        ran = all(_cpu_ticks(pid) > ticks[pid] for pid in writing)
        after = {p: (p.stat().st_mtime_ns, p.stat().st_ino) for p in entry.rglob("*")}
    finally:
        _restart_node(cluster, proc)
    _same_exrs(serial, views, 60)
    return took, sorted(set(after.items()) ^ set(finished.items()))[:5], ran, log.read_text(), len(writing)


def _writers(views: Path) -> dict[int, int]:
    """The Ray workers writing into the dataset entry under ``views``, by process id (from the names
    of their journals, ``journal-<host>-<pid>-<random>.jsonl``, made as a worker joins), and the
    views each has finished (of the 20 of a task; none yet for one that has just joined)."""
    found = {}
    for journal in views.glob("*/journal-*.jsonl"):
        with contextlib.suppress(OSError):
            found[int(journal.stem.rsplit("-", 2)[1])] = journal.read_text().count(".exr")
    return found


def _cpu_ticks(pid: int) -> int:
    """The CPU time ``pid`` has used so far, in clock ticks (user and system)."""
    with contextlib.suppress(OSError):
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])
    return 0
