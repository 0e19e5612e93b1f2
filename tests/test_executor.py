"""Sharding per-frame work over Ray gives what a serial run gives, into the same cache."""

from __future__ import annotations

import json
from pathlib import Path

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


@pytest.mark.slow
def test_ray_simulates_the_scenes_at_once_to_a_serial_runs_frames(tiny_dam, tmp_path, caplog):
    """``simulate --executor ray`` runs each scene as a Ray task asking for the CPUs of its solver
    threads (here 3, on a cluster of 2: at most the largest node's, so that it runs at all) with the
    config's thread count, so its frames are a serial run's to the bit; a sequence cut back after a
    kill resumes on the cluster to the same frames."""
    import numpy as np

    ray = pytest.importorskip("ray")
    from pipeline.frames import load_frame

    body = yaml.safe_load(tiny_dam.read_text())
    body["scenes"] = ["tiny_dam", "tiny_pool"]
    body["simulate"].update(frames=4, threads=3)
    pool = yaml.safe_load((tiny_dam.parent / "scenes" / "tiny_dam.yaml").read_text())
    pool.update(name="tiny_pool", fluid=[{"shape": "box", "lo": [0.3, 0, 0], "hi": [0.6, 0.15, 0.3]}])
    (tiny_dam.parent / "scenes" / "tiny_pool.yaml").write_text(yaml.safe_dump(pool))
    tiny_dam.write_text(yaml.safe_dump(body))
    body.update(data_dir=str(tmp_path / "ray_data"), scene_dir=str(tiny_dam.parent / "scenes"))
    (tmp_path / "ray.yaml").write_text(yaml.safe_dump(body))
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0

    def same_frames() -> None:
        serial = sorted((tiny_dam.parent / "data" / "simulate").iterdir())
        sharded = sorted((tmp_path / "ray_data" / "simulate").iterdir())
        assert [a.name for a in serial] == [b.name for b in sharded] and len(serial) == 2
        for a, b in zip(serial, sharded, strict=True):
            assert (b / "manifest.json").exists()
            for k in range(1, 5):
                for x, y in zip(load_frame(a / f"frame_{k:04d}.npz"), load_frame(b / f"frame_{k:04d}.npz"),
                                strict=True):
                    np.testing.assert_array_equal(x, y)

    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        with caplog.at_level("INFO", logger="deep_ssfr"):
            assert cli.main(["simulate", "--config", str(tmp_path / "ray.yaml"), "--executor", "ray"]) == 0
        assert "ray: 2 tasks on this machine (1 node, 2 CPUs, 2 a task)" in caplog.text
        assert "a task asks for 3 CPUs and the largest node has 2" in caplog.text
        same_frames()
        cut = sorted((tmp_path / "ray_data" / "simulate").iterdir())[1]
        for name in ("manifest.json", "frame_0003.npz", "frame_0004.npz"):
            (cut / name).unlink()  # a run killed after its second frame
        caplog.clear()
        with caplog.at_level("INFO", logger="deep_ssfr"):
            assert cli.main(["simulate", "--config", str(tmp_path / "ray.yaml"), "--executor", "ray"]) == 0
        assert "ray: 1 tasks" in caplog.text and "cached" in caplog.text
        same_frames()
    finally:
        ray.shutdown()


@pytest.mark.slow
def test_a_scene_that_fails_on_ray_leaves_the_others_finished(tiny_dam, tmp_path, capsys):
    """One of two scenes simulated over Ray has no particles (its fluid a corner of the container
    thinner than a particle, which the seeding leaves empty): the
    command fails with that scene's error, and the other scene's entry is finished (a re-run finds
    it cached), not left unfinished behind the failure."""
    ray = pytest.importorskip("ray")

    body = yaml.safe_load(tiny_dam.read_text())
    body.update(scenes=["tiny_dam", "tiny_void"], executor="ray")
    body["simulate"].update(frames=2, threads=1)
    void = yaml.safe_load((tiny_dam.parent / "scenes" / "tiny_dam.yaml").read_text())
    void.update(name="tiny_void", fluid=[{"shape": "box", "lo": [0, 0, 0], "hi": [0.005, 0.005, 0.005]}])
    (tiny_dam.parent / "scenes" / "tiny_void.yaml").write_text(yaml.safe_dump(void))
    tiny_dam.write_text(yaml.safe_dump(body))
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        assert cli.main(["simulate", "--config", str(tiny_dam)]) == 1
        assert "scene 'tiny_void' has no particles" in capsys.readouterr().err
        (done,) = (tiny_dam.parent / "data" / "simulate").glob("tiny_dam-*/manifest.json")
        assert not list((tiny_dam.parent / "data" / "simulate").glob("tiny_void-*/manifest.json"))
        body["scenes"] = ["tiny_dam"]
        tiny_dam.write_text(yaml.safe_dump(body))
        before = done.stat().st_mtime_ns
        assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
        assert done.stat().st_mtime_ns == before
    finally:
        ray.shutdown()


def test_each_tasks_result_is_handed_over_as_it_arrives_while_the_others_run(tmp_path):
    """``run_tasks(on_result=...)`` (what finishes each scene's entry as its simulation returns):
    the second task waits for the mark the first one's handler leaves, so it ends only if that
    handler ran while it was still running (else it gives up after 30 s and says so)."""
    ray = pytest.importorskip("ray")
    mark = tmp_path / "first-handled"

    def task(k: int) -> bool:  # nested, so that it travels by value
        import time

        if k == 0:
            return True
        end = time.monotonic() + 30
        while not mark.exists() and time.monotonic() < end:
            time.sleep(0.05)
        return mark.exists()

    handled = []

    def handle(k: int, result: bool) -> None:
        handled.append(k)
        mark.touch()

    assert run_tasks(lambda k: k * k, [3, 1], on_result=lambda k, r: handled.append((k, r))) == [9, 1]
    assert handled == [(0, 9), (1, 1)]
    handled.clear()
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        assert run_tasks(task, [0, 1], "ray", on_result=handle) == [True, True]
        assert handled == [0, 1]
    finally:
        ray.shutdown()


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
    stat = frame.stat()
    frame.write_bytes(bytes(stat.st_size))  # damaged in place: its recorded size and time still hold
    os.utime(frame, ns=(stat.st_atime_ns, stat.st_mtime_ns))
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


def test_only_a_task_running_long_while_a_slot_is_free_gets_a_backup_copy():
    """The policy of backup copies (:func:`pipeline.executor.overdue`): a task past twice the median
    of the finished ones and the floor, among those holding slots, while a slot is free; the longest
    running first; none for a task that waits for a slot, none twice, none with copies off."""
    from pipeline.executor import overdue

    started = {0: 0.0, 1: 5.0, 2: 1.0, 3: 50.0}
    # tasks 0 and 2 have run 60 and 59 s, over 2 x 20 s; 1 has run 55 s; 3 only 10 s
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 8, 60.0, 2.0, floor=1.0) == [0, 2, 1]
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 6, 60.0, 2.0, floor=1.0) == [0, 2]  # two slots free
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 5, 60.0, 2.0, floor=1.0) == [0]
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 4, 60.0, 2.0, floor=1.0) == []  # none free
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 2, 60.0, 2.0, floor=1.0) == []  # 2 and 3 wait
    assert overdue([0, 1, 2, 3], started, [20.0], {0}, 6, 60.0, 2.0, floor=1.0) == [2]  # 0's copy holds one
    assert overdue([0, 1, 2, 3], started, [29.0], set(), 8, 60.0, 2.0, floor=1.0) == [0, 2]  # over 58 s only
    assert overdue([0, 1, 2, 3], started, [20.0], set(), 8, 60.0, 2.0, floor=58.5) == [0, 2]  # the floor
    assert overdue([0, 1, 2, 3], started, [], set(), 8, 60.0, 2.0) == []  # nothing finished to compare with
    assert overdue([0, 1, 2, 3], started, [1.0], set(), 8, 60.0, 0.0) == []  # copies off


def test_the_backup_factor_comes_from_the_environment_or_a_clear_error(monkeypatch):
    from pipeline.executor import BACKUP_FACTOR, BACKUP_FACTOR_ENV, backup_factor

    monkeypatch.delenv(BACKUP_FACTOR_ENV, raising=False)
    assert backup_factor() == BACKUP_FACTOR
    monkeypatch.setenv(BACKUP_FACTOR_ENV, "0")
    assert backup_factor() == 0
    monkeypatch.setenv(BACKUP_FACTOR_ENV, "1.5")
    assert backup_factor() == 1.5
    for bad in ("fast", "-1", "nan"):
        monkeypatch.setenv(BACKUP_FACTOR_ENV, bad)
        with pytest.raises(ValueError, match=f"^DEEP_SSFR_RAY_BACKUP_FACTOR='{bad}': a number, 0 or more"):
            backup_factor()


@pytest.mark.slow
def test_a_straggling_ray_task_is_overtaken_by_its_backup_copy(tmp_path, monkeypatch, caplog):
    """Three tasks on three CPUs, the first try of one hanging (a slow or hung node): once it has run
    over the floor and twice the others' time, a backup copy runs it on the slot they freed, the run
    ends with every result in order long before the hung try would have, and the hung try's worker
    is killed (cancelled and waited for). Ray answers the cancel as the worker starts to exit, so its
    process may take a moment more to go: the check allows 5 s, far short of the 90 s hang."""
    import os
    import time

    ray = pytest.importorskip("ray")
    from pipeline import executor

    monkeypatch.setattr(executor, "BACKUP_MIN_S", 2.0)
    monkeypatch.delenv(executor.BACKUP_FACTOR_ENV, raising=False)
    hung = tmp_path / "hung"

    def task(k):
        if k == 2:
            try:
                os.close(os.open(hung, os.O_CREAT | os.O_EXCL))  # the first try only
            except FileExistsError:
                return k, os.getpid()
            hung.write_text(str(os.getpid()))
            time.sleep(90)
        time.sleep(0.5)
        return k, os.getpid()

    ray.init(num_cpus=3, include_dashboard=False, configure_logging=False, log_to_driver=False)
    try:
        start = time.monotonic()
        with caplog.at_level("INFO", logger="deep_ssfr"):
            done = run_tasks(task, [0, 1, 2], "ray")
        took = time.monotonic() - start
        pid = int(hung.read_text())

        def alive() -> bool:
            status = Path(f"/proc/{pid}/status")
            try:
                return "zombie" not in status.read_text()
            except FileNotFoundError:
                return False

        deadline = time.monotonic() + 5
        while alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        gone = not alive()
    finally:
        ray.shutdown()
    assert [k for k, _ in done] == [0, 1, 2]
    assert took < 60, f"{took:.0f} s: the backup copy should end the run, not the hung try"
    assert "ray: task 3 of 3 has run" in caplog.text and "a backup copy started" in caplog.text
    assert "ray: 1 backup copy, 1 of them finished first" in caplog.text
    assert pid != done[2][1], "the result is the backup copy's"
    assert gone, "the hung try's worker was not killed"
