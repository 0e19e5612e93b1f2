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
def test_a_command_joins_one_cluster_for_all_its_work():
    """Inside ``cluster_scope`` (every command's) the calls share the cluster the first one started;
    outside one, each call leaves nothing running."""
    ray = pytest.importorskip("ray")
    from pipeline.executor import cluster_scope

    def _job(_):  # defined here: a test module's functions travel by value only when nested
        import ray

        return ray.get_runtime_context().get_node_id()  # a new cluster, a new node

    with cluster_scope():
        first = run_tasks(_job, [0, 1], "ray")
        assert ray.is_initialized()
        assert run_tasks(_job, [0], "ray")[0] == first[0] == first[1]
    assert not ray.is_initialized()
    run_tasks(_job, [0], "ray")
    assert not ray.is_initialized()


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
