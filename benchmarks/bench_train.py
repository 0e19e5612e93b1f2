"""Refiner speed: training images/s on 256x256 crops and inference ms per frame at 512^2 and 1024^2.

    .venv/bin/python benchmarks/bench_train.py [--config configs/default.yaml] [--steps 6]

On this CPU (AVX512-BF16) training runs under bfloat16 autocast in channels-last layout: 9.1 images/s
on configs/generalize.yaml's refiner, against 3.7 in float32 and the default layout (2026-12-06).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pipeline.config_files import load
from pipeline.device import choose_device
from pipeline.model.data import InputSpec
from pipeline.model.networks import count_parameters
from pipeline.model.trainer import Refiner, predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--crop", type=int, default=256)
    args = parser.parse_args()
    loaded = load(args.config)
    cfg = loaded.config.train
    device = choose_device(loaded.config.device)
    refiner = Refiner(cfg, device, seed=0)
    rng = np.random.default_rng(0)
    c = InputSpec.of(cfg).channels
    x = rng.normal(size=(cfg.batch_size, c, args.crop, args.crop)).astype(np.float32)
    y = rng.normal(size=(cfg.batch_size, 3, args.crop, args.crop)).astype(np.float32).clip(-1, 1)
    print(f"device {device}, torch {torch.__version__}, {torch.get_num_threads()} threads; generator "
          f"{count_parameters(refiner.generator) / 1e6:.2f} M, discriminator "
          f"{count_parameters(refiner.discriminator) / 1e6:.2f} M parameters; autocast "
          f"{str(refiner.autocast_dtype).removeprefix('torch.')} (train.mixed_precision)")
    refiner.train_step(x, y)  # warm-up
    start = time.perf_counter()
    for _ in range(args.steps):
        refiner.train_step(x, y)
    wall = time.perf_counter() - start
    print(f"training  {args.crop}x{args.crop} crops, batch {cfg.batch_size}: "
          f"{args.steps * cfg.batch_size / wall:6.2f} images/s ({1000 * wall / args.steps:.0f} ms/step)")
    for size in (512, 1024):
        frame = rng.normal(size=(c, size, size)).astype(np.float32)
        predict(refiner.generator, frame, refiner.device)
        runs = 3
        start = time.perf_counter()
        for _ in range(runs):
            predict(refiner.generator, frame, refiner.device)
        print(f"inference {size}x{size}: {1000 * (time.perf_counter() - start) / runs:7.1f} ms/frame")


if __name__ == "__main__":
    main()
