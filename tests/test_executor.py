"""Sharding per-frame work over Ray gives what a serial run gives, into the same cache."""

from __future__ import annotations

import json

import pytest
import yaml

from pipeline.executor import run_tasks, shards
from stages import cli


def test_shards_cover_everything_once_in_order():
    for n in (0, 1, 5, 17):
        for k in (1, 2, 3, 8):
            parts = shards(list(range(n)), k)
            assert [x for part in parts for x in part] == list(range(n))
            assert all(parts) and len(parts) <= max(k, 1)
            assert max(map(len, parts), default=0) - min(map(len, parts), default=0) <= 1
    assert run_tasks(lambda x: x * x, [3, 1, 2]) == [9, 1, 4]
    with pytest.raises(ValueError, match="unknown executor"):
        run_tasks(abs, [1], "dask")


@pytest.mark.slow
def test_ray_dataset_render_and_evaluate_equal_a_serial_run(tiny_dam, tmp_path):
    pytest.importorskip("ray")
    body = yaml.safe_load(tiny_dam.read_text())
    body["dataset"] = {"width": 48, "height": 48, "frame_stride": 2, "holdout_scenes": ["tiny_dam"]}
    body["evaluate"] = {"methods": ["bilateral", "nrf"], "frames_per_sequence": 2}
    body["render"] = {"width": 48, "height": 48, "method": "nrf", "comparison": False}
    serial = tiny_dam.parent / "data"
    tiny_dam.write_text(yaml.safe_dump(body))
    body["data_dir"] = str(tmp_path / "ray_data")
    body["scene_dir"] = str(tiny_dam.parent / "scenes")
    (tmp_path / "ray.yaml").write_text(yaml.safe_dump(body))
    for stage in ("dataset", "render", "evaluate"):
        assert cli.main([stage, "--config", str(tiny_dam)]) == 0
        assert cli.main([stage, "--config", str(tmp_path / "ray.yaml"), "--executor", "ray"]) == 0
    for stage, count in (("dataset", 6), ("render", 6)):
        (a,) = (serial / stage).iterdir()
        (b,) = (tmp_path / "ray_data" / stage).iterdir()
        assert a.name == b.name, "the executor is not part of the key: both runs fill the same entry"
        files = sorted(p.relative_to(a) for p in a.rglob("*.exr"))
        assert len(files) == count and files == sorted(p.relative_to(b) for p in b.rglob("*.exr"))
        for f in files:
            assert (a / f).read_bytes() == (b / f).read_bytes(), f

    assert evaluation_metrics(serial) == evaluation_metrics(tmp_path / "ray_data")


def evaluation_metrics(root):
    """The evaluate entry's metrics under ``root`` (a data_dir) without their timings."""
    (entry,) = (root / "evaluate").iterdir()
    data = json.loads((entry / "metrics.json").read_text())
    sized = [(d["overall"], d["sequences"]) for d in data["sizes"].values()]
    for overall, sequences in [(data["overall"], data["sequences"]), *sized]:
        for table in [overall, *(s["methods"] for s in sequences)]:
            for row in table.values():
                row.pop("ms_per_frame", None)  # timings differ, everything else must not
    return data


@pytest.mark.slow
def test_a_command_joins_one_cluster_for_all_its_work(caplog):
    """Inside ``cluster_scope`` (every command's) the calls share the cluster the first one started;
    outside one, each call leaves nothing running. Each call logs the nodes its tasks ran on."""
    ray = pytest.importorskip("ray")
    caplog.set_level("INFO")
    from pipeline.executor import cluster_scope

    def _job(_):  # defined here: a test module's functions travel by value only when nested
        import ray

        return ray.get_runtime_context().get_node_id()  # a new cluster, a new node

    with cluster_scope():
        first = run_tasks(_job, [0, 1], "ray")
        assert ray.is_initialized()
        assert f"ray: the tasks ran on {ray.util.get_node_ip_address()} (2)" in caplog.text
        assert run_tasks(_job, [0], "ray")[0] == first[0] == first[1]
    assert not ray.is_initialized()
    run_tasks(_job, [0], "ray")
    assert not ray.is_initialized()


KEEPALIVE = """if True:
    import json
    from pipeline.executor import connected
    with connected("ray"):
        from ray._raylet import Config
        print(json.dumps([Config.grpc_client_keepalive_time_ms(), Config.grpc_client_keepalive_timeout_ms()]))
"""


@pytest.mark.slow
def test_a_driver_pings_its_ray_connections_every_minute_unless_told_otherwise():
    """Ray reads its settings once, when imported: the driver's keepalive (a hung node's tasks found
    lost in about 100 s, not Ray's 7 minutes) is set before that, and a user's own setting wins."""
    pytest.importorskip("ray")
    import os
    import subprocess
    import sys

    from pipeline.executor import RAY_KEEPALIVE
    from tests.conftest import ROOT

    def seen(**env: str) -> list[int]:
        clean = {k: v for k, v in os.environ.items() if k not in RAY_KEEPALIVE}
        done = subprocess.run([sys.executable, "-c", KEEPALIVE], cwd=ROOT, env={**clean, **env}, check=True,
                              capture_output=True, text=True, timeout=120)
        return json.loads(done.stdout.strip().splitlines()[-1])

    assert seen() == [60000, 20000]
    assert seen(RAY_grpc_client_keepalive_time_ms="90000") == [90000, 20000]


@pytest.mark.slow
def test_a_failed_ray_task_is_the_stages_one_line_error(tiny_dam, capsys):
    """A task's own error reaches the stage as a local run's would (the corrupt frame named, in one
    line, not the remote traceback), and Ray's failures, here a worker that dies at every one of its
    retries, as one line naming the cluster."""
    import os

    ray = pytest.importorskip("ray")
    body = yaml.safe_load(tiny_dam.read_text())
    body["dataset"] = {"width": 32, "height": 32, "frame_stride": 1, "holdout_scenes": ["tiny_dam"]}
    tiny_dam.write_text(yaml.safe_dump(body))
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    (frame,) = tiny_dam.parent.glob("data/simulate/*/frame_0004.npz")
    frame.write_bytes(bytes(frame.stat().st_size))  # damaged in place: its recorded size still holds
    capsys.readouterr()
    assert cli.main(["dataset", "--config", str(tiny_dam), "--executor", "ray"]) == 1
    (line,) = [x for x in capsys.readouterr().err.splitlines() if "error" in x]
    assert line.startswith(f"dataset: error: corrupt cache file {frame} ("), line

    def dies(_):
        os._exit(3)

    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        with pytest.raises(RuntimeError, match=r"^a Ray task on this machine failed \(WorkerCrashedError: .*\); "
                                               r"the files it finished are kept and a re-run resumes$"):
            run_tasks(dies, [0], "ray")
        with pytest.raises(ValueError, match="^math domain error$") as raised:
            run_tasks(lambda x: __import__("math").sqrt(x), [1, -1], "ray")
        assert type(raised.value) is ValueError, "the task's own error, not Ray's wrapper of it"
    finally:
        ray.shutdown()


@pytest.mark.slow
def test_ray_tasks_of_a_gpu_run_each_hold_a_gpu():
    """A CUDA run's Ray tasks ask for their share of a GPU, so each gets its own instead of all of
    them crowding onto the node's first: on a cluster told it has two GPUs each task is given one
    (its ``CUDA_VISIBLE_DEVICES``, so its ``cuda:0``), the work is cut into one shard per GPU, and a
    CPU run's tasks are given none."""
    import os

    ray = pytest.importorskip("ray")
    from pipeline.executor import TASKS_PER_GPU, cluster_slots

    ray.init(num_cpus=3, num_gpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        assert cluster_slots("ray", "cuda:0") == 2 * TASKS_PER_GPU and cluster_slots("ray", "cpu") == 3

        def sees(_):
            return [str(i) for i in ray.get_gpu_ids()], os.environ.get("CUDA_VISIBLE_DEVICES")

        for ids, visible in run_tasks(sees, [0, 1], "ray", device="cuda"):
            assert len(ids) == 1 and visible == ids[0]
        for ids, visible in run_tasks(sees, [0, 1], "ray", device="cpu"):
            assert ids == [] and not visible
    finally:
        ray.shutdown()
