"""Training at scale: crops read lazily from disk, and data-parallel (DDP) runs of 2 CPU processes.

The lazy dataset must give the same batches for any number of DataLoader workers and after a
resume; the in-memory path must train exactly as it did before either existed; a DDP run must
train, resume like a straight run and write checkpoints that ``load_refiner`` reads; and
``torchrun -m stages.cli train`` must handle the cache entry on rank 0 alone.
"""

from __future__ import annotations

import hashlib
import math
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
import torch.multiprocessing as mp

from pipeline.camera import Camera, look_at
from pipeline.config import TrainConfig
from pipeline.dataset import view_attributes
from pipeline.model.data import (
    CropDataset,
    DiskBatches,
    Frame,
    InputSpec,
    MemoryBatches,
    draw_crop,
    held_window,
    load_frame,
    random_crops,
)
from pipeline.model.trainer import Refiner, seed_everything
from tests.conftest import ROOT

SPEC = InputSpec(True, "ellipsoid")
TINY = {"crop": 32, "batch_size": 2, "crops_per_frame": 2, "gen_base_channels": 8, "gen_res_blocks": 1,
        "disc_base_channels": 8, "disc_layers": 2, "val_frames": 2}


def _ball_channels(size: int, k: int) -> dict[str, np.ndarray]:
    """Dataset channels of a frame showing a noisy ball (the ellipsoid splat's names) and its target."""
    rng = np.random.default_rng(k)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    cx, cy, r = size * (0.35 + 0.3 * rng.random()), size * (0.35 + 0.3 * rng.random()), size * 0.3
    dx, dy = (xx - cx) / r, (yy - cy) / r
    inside = dx**2 + dy**2 < 1
    nz = np.sqrt(np.clip(1 - dx**2 - dy**2, 0, 1))
    target = np.stack([dx, -dy, nz]) * inside
    noisy = target + 0.1 * rng.standard_normal(target.shape).astype(np.float32) * inside
    depth = (2.0 - 0.3 * nz) * inside
    ch = {f"target.N.{a}": target[i] for i, a in enumerate("XYZ")}
    ch.update({f"aniso_bilateral.N.{a}": noisy[i] for i, a in enumerate("XYZ")})
    ch.update({"aniso.Z": depth + 0.01 * rng.standard_normal(depth.shape) * inside, "aniso_bilateral.Z": depth,
               "aniso.A": inside.astype(np.float32)})
    return {n: np.ascontiguousarray(v, dtype=np.float32) for n, v in ch.items()}


def _write_frames(folder: Path, count: int, size: int = 48) -> list[Path]:
    """``count`` dataset-like EXR frames of ``size`` px in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(count):
        path = folder / f"frame_{k:04d}.exr"
        channels = _ball_channels(size, k)
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                  **view_attributes(Camera(look_at((0, 0, 2), (0, 0, 0)), 40.0, size, size), 0.01,
                                    channels["aniso.A"])}
        OpenEXR.File(header, channels).write(str(path))
        paths.append(path)
    return paths


def _synthetic_frames(count: int = 3, size: int = 40) -> list[Frame]:
    """Frames with a fluid disc in the target, the last one with none (the crop rule's other branch)."""
    frames = []
    for k in range(count):
        rng = np.random.default_rng(100 + k)
        yy, xx = np.mgrid[0:size, 0:size]
        disc = (yy - size * 0.3 * (k + 1)) ** 2 + (xx - size * 0.6) ** 2 < (size * 0.2) ** 2
        disc = disc if k < count - 1 else np.zeros((size, size), bool)
        target = (rng.standard_normal((3, size, size)) * disc).astype(np.float32)
        frames.append(Frame(rng.standard_normal((5, size, size)).astype(np.float32), target, f"f{k}", disc))
    return frames


def test_the_crop_rule_draws_the_crops_it_drew_before_disk_data_existed():
    x, y = random_crops(_synthetic_frames(), 16, 24, np.random.default_rng(11))
    # recorded with random_crops as it was before draw_crop was split out of it
    assert hashlib.sha256(x.tobytes() + y.tobytes()).hexdigest() == \
        "4446398abfd775f99397cc606b0730c6e94600734b5dc6d3236b8ccf3869bb49"


@pytest.fixture
def one_thread():
    """torch on one thread (a tiny network runs fastest so on a shared machine), restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_memory_data_trains_exactly_as_the_loop_before_disk_data_and_ddp(tmp_path, one_thread):
    from pipeline.model.train import MEMORY_WINDOW_PX, fit

    paths = _write_frames(tmp_path / "frames", 5)
    cfg = TrainConfig(epochs=2, threads=1, **TINY)
    fit(tmp_path / "run", cfg, 3, paths[:4], paths[4:], "cpu")
    # memory training holds float16 windows of the frames (here whole: 48 px) and turns crops
    held = np.random.default_rng([3, 7])
    frames = [held_window(load_frame(p, SPEC), MEMORY_WINDOW_PX, held) for p in paths[:4]]
    refiner = Refiner(cfg, "cpu", seed=3)
    for epoch in (1, 2):  # the training loop as it was
        rng = np.random.default_rng([3, epoch])
        seed_everything(3 * 100_003 + epoch)
        for _ in range(math.ceil(4 * cfg.crops_per_frame / cfg.batch_size)):
            refiner.train_step(*random_crops(frames, cfg.crop, cfg.batch_size, rng, rotate=cfg.rotations))
        refiner.end_epoch()
    saved = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    for k, v in refiner.generator.state_dict().items():
        assert torch.equal(saved["generator"][k], v), k


def _epoch_batches(source, epoch: int, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.asarray(x), np.asarray(y)) for x, y in source.batches(epoch, steps)]


def test_disk_batches_are_equal_for_0_and_2_workers_after_a_resume_and_split_over_processes(tmp_path):
    paths = _write_frames(tmp_path, 4)
    steps, batch = 3, 4

    def source(workers: int, rank: int = 0, world: int = 1) -> DiskBatches:
        return DiskBatches(CropDataset(paths, 16, 5, SPEC, cached_frames=2), steps, batch, workers,
                           rank, world)

    straight = source(0)
    first, second = _epoch_batches(straight, 1, steps), _epoch_batches(straight, 2, steps)
    resumed = _epoch_batches(source(2), 2, steps)  # a fresh process starting at epoch 2, two workers
    assert len(second) == len(resumed) == steps
    for (xa, ya), (xb, yb) in zip(second, resumed, strict=True):
        # the same crops; a worker resamples them to the working scale on one torch thread, which can
        # round a bilinear weight one ulp apart from the two-thread main process
        assert xa.shape == (batch, SPEC.channels, 16, 16)
        np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-6)
        np.testing.assert_allclose(ya, yb, rtol=0, atol=1e-6)
    assert not np.array_equal(first[0][0], second[0][0]), "each epoch draws new crops"
    halves = [_epoch_batches(source(0, rank, 2), 2, steps) for rank in (0, 1)]
    for s in range(steps):  # two processes read the two halves of each global batch
        assert np.array_equal(np.concatenate([halves[0][s][0], halves[1][s][0]]), second[s][0])
    memory = MemoryBatches([load_frame(p, SPEC) for p in paths], 16, batch, 5, rank=1, world=2)
    whole = MemoryBatches(memory.frames, 16, batch, 5)
    for (xa, _), (xb, _) in zip(_epoch_batches(memory, 1, steps), _epoch_batches(whole, 1, steps), strict=True):
        assert np.array_equal(xa, xb[batch // 2:])


def test_a_disk_sample_is_the_shared_crop_rule_on_its_frame(tmp_path):
    paths = _write_frames(tmp_path, 3)
    dataset = CropDataset(paths, 16, 9, SPEC, cached_frames=0)
    x, y = dataset[(4, 17)]
    rng = np.random.default_rng([9, 4, 17])
    want = draw_crop(load_frame(paths[int(rng.integers(3))], SPEC), 16, rng)
    assert np.array_equal(x, want[0]) and np.array_equal(y, want[1])
    centres = [np.abs(dataset[(1, i)][1][:, 8, 8]).sum() > 0 for i in range(60)]
    assert np.mean(centres) > 0.7, "crops are centred on fluid 90% of the time"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank: int, port: int, folder: str) -> None:
    """One of two gloo processes, as torchrun would start it: a straight 2-epoch run reading with a
    DataLoader worker, a 1-epoch run continued to 2 reading in-process, a batch that does not
    split over the processes, and a time limit that rank 1's clock alone says is reached."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE="2", RANK=str(rank),
                      LOCAL_RANK=str(rank))
    from pipeline.model.train import TrainingError, fit

    paths = sorted(Path(folder, "frames").glob("*.exr"))
    cfg = {**TINY, "data": "disk", "loader_workers": 0, "threads": 1}
    best = fit(Path(folder, "straight"), TrainConfig(epochs=2, **{**cfg, "loader_workers": 1}), 0, paths[:4],
               paths[4:], "cpu")
    fit(Path(folder, "resumed"), TrainConfig(epochs=1, **cfg), 0, paths[:4], paths[4:], "cpu")
    fit(Path(folder, "resumed"), TrainConfig(epochs=2, **cfg), 0, paths[:4], paths[4:], "cpu")
    Path(folder, f"best-{rank}.txt").write_text(repr(best))
    with pytest.raises(TrainingError, match="does not split over 2 processes"):
        fit(Path(folder, "odd"), TrainConfig(epochs=1, **{**cfg, "batch_size": 3}), 0, paths[:4], paths[4:], "cpu")
    if rank == 1:  # a clock far ahead of rank 0's: by its own reading it would stop after an epoch
        import types

        import pipeline.model.train as training

        real = time.perf_counter
        training.time = types.SimpleNamespace(perf_counter=lambda: 1000 * real())
    fit(Path(folder, "clock"), TrainConfig(epochs=2, time_limit_minutes=1, **cfg), 0, paths[:4], paths[4:], "cpu")


@pytest.mark.slow
def test_ddp_of_two_cpu_processes_trains_resumes_like_a_straight_run_and_its_checkpoint_loads(tmp_path):
    """Disk data under DDP: workers or not, straight or resumed, the same weights."""
    from pipeline.model.inference import load_refiner

    _write_frames(tmp_path / "frames", 5)
    mp.spawn(_ddp_worker, args=(_free_port(), str(tmp_path)), nprocs=2)
    assert (tmp_path / "best-0.txt").read_text() == (tmp_path / "best-1.txt").read_text()
    straight = torch.load(tmp_path / "straight" / "last.pt", weights_only=True)
    resumed = torch.load(tmp_path / "resumed" / "last.pt", weights_only=True)
    assert straight["epoch"] == resumed["epoch"] == 2
    assert not any(k.startswith("module.") for k in straight["generator"])
    for k, v in straight["generator"].items():
        assert torch.equal(v, resumed["generator"][k]), k
    assert [h["processes"] for h in straight["history"]] == [2, 2]
    refiner = load_refiner(tmp_path / "straight" / "best.pt")
    frame = load_frame(tmp_path / "frames" / "frame_0004.exr", SPEC)
    assert np.isfinite(refiner(frame.inputs, frame.fluid)).all()
    assert not (tmp_path / "odd" / "last.pt").exists()
    assert torch.load(tmp_path / "clock" / "last.pt", weights_only=True)["epoch"] == 2  # rank 0's clock decides
    assert not list(tmp_path.rglob("*.tmp-*"))


def _torchrun(config: str) -> subprocess.Popen:
    """``torchrun --standalone --nproc_per_node 2 -m stages.cli train --config CONFIG``, stderr piped."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "stages.cli", "train", "--config", config]
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_torchrun_stage_claims_the_entry_on_rank_0_and_its_checkpoint_loads(tmp_path):
    """Rank 0 queues for the entry's lock while rank 1 waits for it; then they train, rank 0 writes the
    manifest and frees the lock, and a second launch is a cache hit on both ranks."""
    import filelock

    from pipeline.model.inference import load_refiner
    from stages.common import StageOptions, make_run
    from stages.train import collect, train_entry
    from tests.test_model import _tiny_train_config

    config = _tiny_train_config(tmp_path, "ddp")
    run = make_run(StageOptions(config))
    entry = train_entry(run, collect(run)[0])  # builds the dataset here, once
    held = filelock.FileLock(entry.lock_path)
    entry.lock_path.parent.mkdir(parents=True, exist_ok=True)
    held.acquire()
    proc = _torchrun(config)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    queued = f"another run is writing {entry.final_dir}; waiting for it"
    deadline = time.monotonic() + 60
    while not any(queued in line for line in lines) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    time.sleep(1.0)  # rank 1 waits without timing out, and nothing trains yet
    assert any(queued in line for line in lines), "".join(lines)
    assert proc.poll() is None and not (entry.final_dir / "last.pt").exists(), "".join(lines)
    held.release()
    assert proc.wait(timeout=120) == 0, "".join(lines)
    reader.join()
    manifest = entry.manifest()
    assert manifest["epochs"] == 2 and manifest["processes"] == 2
    assert load_refiner(entry.final_dir / "best.pt").splat == "ellipsoid"
    with filelock.FileLock(entry.lock_path).acquire(timeout=0):  # free again
        pass
    again = _torchrun(config)
    _, err = again.communicate(timeout=120)
    assert again.returncode == 0 and "train: cached (2 epochs)" in err, err
    assert err.count("train: cached") == 1, "rank 1 logs warnings only"


def test_a_process_group_that_cannot_form_says_what_to_set(monkeypatch):
    """A failed join names the rank and the two settings of a node with several networks; with
    GLOO_SOCKET_IFNAME unset, the interface that reaches the master is chosen before gloo binds."""
    from pipeline.model import distributed

    seen = {}

    def refuse(backend, timeout, **_):
        seen["ifname"], seen["timeout"] = os.environ.get("GLOO_SOCKET_IFNAME"), timeout
        raise RuntimeError("Gloo connectFullMesh failed with timed out connecting")

    monkeypatch.setattr(distributed.dist, "init_process_group", refuse)
    monkeypatch.setattr(distributed, "_WORLD", None)
    monkeypatch.setenv("GLOO_SOCKET_IFNAME", "")  # recorded as it was, so start()'s choice is undone after
    monkeypatch.delenv("GLOO_SOCKET_IFNAME")
    for k, v in {"WORLD_SIZE": "2", "RANK": "1", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1"}.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(RuntimeError, match=r"\(rank 1 of 2, waited up to 300 s: DEEP_SSFR_DIST_TIMEOUT\)\. "
                                           r".*--local-addr.*GLOO_SOCKET_IFNAME"):
        distributed.start("cpu")
    assert seen["ifname"] == "lo" and seen["timeout"].total_seconds() == distributed.STEP_TIMEOUT_S == 300


def test_the_training_groups_timeout_is_read_from_the_environment(monkeypatch):
    """``DEEP_SSFR_DIST_TIMEOUT`` bounds how long a node waits for a peer; a value that is not a positive
    number of seconds is an error naming the variable, not torch's default."""
    from pipeline.model.distributed import step_timeout

    monkeypatch.setenv("DEEP_SSFR_DIST_TIMEOUT", "12.5")
    assert step_timeout().total_seconds() == 12.5
    for bad in ("0", "-3", "soon", "inf", "nan"):
        monkeypatch.setenv("DEEP_SSFR_DIST_TIMEOUT", bad)
        with pytest.raises(ValueError, match=f"must be a positive number of seconds, got '{bad}'"):
            step_timeout()


def _waiting_worker(rank: int, port: int, folder: str, case: str) -> None:
    """One of two gloo processes with a 2 s timeout, in the rank-0-works waits of ``case``; what each
    saw goes to ``<folder>/<case>-<rank>.txt``."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE="2", RANK=str(rank),
                      LOCAL_RANK=str(rank), DEEP_SSFR_DIST_TIMEOUT="2")
    from pipeline.model import distributed

    world = distributed.start("cpu")
    seen = []
    if case == "work":  # longer than the timeout, then a failure, then the peer gone while rank 0 works
        with world.while_main_works("working long"):
            if world.is_main:
                time.sleep(5)
        seen.append(f"waited {world.share(rank)}")
        try:
            with world.while_main_works("checking"):
                if world.is_main:
                    raise ValueError("a bad frame")
        except (ValueError, RuntimeError) as exc:
            seen.append(f"{type(exc).__name__}: {exc}")
        if not world.is_main:
            Path(folder, f"{case}-{rank}.txt").write_text("\n".join(seen))
            os._exit(0)  # its connections close while rank 0 works
        try:
            with world.while_main_works("writing"):
                time.sleep(3)
                seen.append("wrote")
        except RuntimeError as exc:
            seen.append(f"lost: {exc}")
    else:  # "silent": rank 0 is stopped in the block (connections open, nothing answers)
        began = time.monotonic()
        try:
            with world.while_main_works("validating"):
                if world.is_main:
                    Path(folder, "stop-me").touch()
                    time.sleep(60)
        except RuntimeError as exc:
            seen.append(f"RuntimeError after {time.monotonic() - began:.0f} s: {exc}")
    Path(folder, f"{case}-{rank}.txt").write_text("\n".join(seen))


@pytest.mark.slow
def test_the_others_wait_for_rank_0s_long_work_and_a_lost_peer_ends_either_side_within_the_timeout(tmp_path):
    """While rank 0 works alone (a cache lock, validation) its heartbeats keep the others waiting past
    the group's timeout; a failure in its work fails the others too; a peer that ends while rank 0
    works fails rank 0 once its work is done; and a rank 0 that stops answering without closing its
    connections (a node cut off) fails the others within the timeout, where a barrier waits for ever."""
    import multiprocessing
    import signal

    spawn = multiprocessing.get_context("spawn")

    def pair(case: str) -> list:
        port = _free_port()
        procs = [spawn.Process(target=_waiting_worker, args=(r, port, str(tmp_path), case)) for r in (0, 1)]
        for p in procs:
            p.start()
        return procs

    procs = pair("work")
    for p in procs:
        p.join(60)
    zero, one = ((tmp_path / f"work-{r}.txt").read_text().splitlines() for r in (0, 1))
    assert zero[0] == one[0] == "waited 0"
    assert zero[1] == "ValueError: a bad frame"
    assert one[1] == "RuntimeError: rank 0 failed while checking (its log says why)"
    assert zero[2] == "wrote" and zero[3].startswith("lost: ") and zero[3].endswith("(while writing)"), zero

    procs = pair("silent")
    deadline = time.monotonic() + 60
    while not (tmp_path / "stop-me").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(procs[0].pid, signal.SIGSTOP)
    try:
        procs[1].join(30)
        (said,) = (tmp_path / "silent-1.txt").read_text().splitlines()
    finally:
        procs[0].kill()
        procs[0].join()
    took = int(said.split()[2])
    assert said.startswith("RuntimeError after") and took <= 2 + 3, said
