"""Costs of the metaball method per frame on this machine: the particles' ellipsoids (the anisotropy
of what the camera sees, as the renderer computes it, when the generator's balls are ellipsoids), the
network's input (drawn at the working scale, whose size it prints), the generator's forward pass (the
shipped weights) and the whole method from particles to G-buffers at the view's size, ellipsoids
included, against the ray-marched metaball surface it stands in for, at 256 to 1024 px. The thesis
reports 22 ms a frame at 512 x 512 on a GTX 1080 (18 ms of network); issue 54 asks for at most 150 ms
at 512 on this CPU, all of it included.

Frame: a PBF dam break of 49,140 particles (r = 7.4 mm) framed whole by the camera.

With ``--heldout CONFIG`` it times the method instead on the frames the issue's goals are scored on:
every held-out sequence and imported frame of the config's evaluation, ``--frames`` spread over each,
at each size, as ``deep-ssfr render`` computes it for one view (``pipeline.methods.normal_source``:
the ellipsoids of what the camera sees, the sphere splat's thickness, the field, the network and
the resampling, nothing shared between frames), one process on an otherwise idle machine.

    .venv/bin/python benchmarks/bench_metaball.py [--sizes 256 512 1024] [--repeat 3] [--no-march] [--weights PT]
    .venv/bin/python benchmarks/bench_metaball.py --heldout configs/generalize.yaml --sizes 512 [--frames 4]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import _camera_for, _pbf_frame  # noqa: E402
from bench_render import _best_ms as _median_ms  # noqa: E402

from pipeline.config import DatasetConfig  # noqa: E402
from pipeline.metaball.inference import MetaballNet  # noqa: E402
from pipeline.metaball.train import SHIPPED_WEIGHTS, predict  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.surface import particle_ellipsoids, seen_kernels  # noqa: E402


def heldout(config: str, sizes: list[int], frames: int, repeat: int) -> None:
    """Per held-out sequence: particles, and the median and slowest frame of the metaball method."""
    from functools import partial

    import numpy as np

    from pipeline.camera import camera_for_frame
    from pipeline.device import warp_device
    from pipeline.frames import frame_name, load_frame, spread
    from pipeline.methods import normal_source
    from pipeline.screen import ScreenSpace
    from stages import evaluate, render
    from stages.common import StageOptions, make_run

    for size in sizes:
        run = make_run(StageOptions(config=config), {"dataset": {"width": size, "height": size}})
        _, metaball, _ = render.networks(make_run(StageOptions(config=config)), ("metaball",))
        wdev = warp_device(run.device)
        ss, launch = ScreenSpace(wdev), Launcher(wdev)
        p = run.config.dataset
        print(f"\nmetaball method at {size} x {size}, all of it included (ms a frame; {frames} frames a sequence, "
              f"the median of {repeat} runs each)")
        print(f"{'sequence':>40s} {'particles':>10s} {'median ms':>10s} {'max ms':>8s}")
        medians, slowest = [], []
        for seq in evaluate.sequences(run):
            times, counts = [], []
            for r in spread(seq.records, frames):
                x, _ = load_frame(seq.sim_dir / frame_name(r["frame"]))
                i = seq.records.index(r)
                cam = camera_for_frame(seq.scene.cameras, seq.camera, i, len(seq.records), p.width, p.height)
                times.append(_median_ms(partial(normal_source, "metaball", x, seq.particle_radius, cam, p, ss, launch,
                                                metaball=metaball), repeat))
                counts.append(len(x))
            medians.append(float(np.median(times)))
            slowest.append(max(times))
            print(f"{seq.scene.name + ' / ' + seq.camera:>40s} {int(np.median(counts)):>10,d} {medians[-1]:>10.1f} "
                  f"{slowest[-1]:>8.1f}")
        print(f"{'mean of the sequences':>40s} {'':>10s} {np.mean(medians):>10.1f} {max(slowest):>8.1f}")
        ss.close()
        launch.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--particles", type=int, default=49_140)
    ap.add_argument("--no-march", action="store_true", help="skip the ray-marched surface (seconds a frame)")
    ap.add_argument("--weights", type=Path, default=SHIPPED_WEIGHTS, help="generator checkpoint")
    ap.add_argument("--heldout", metavar="CONFIG", help="time the held-out sequences of this config's evaluation")
    ap.add_argument("--frames", type=int, default=4, help="frames a held-out sequence (--heldout)")
    args = ap.parse_args()
    if args.heldout:
        heldout(args.heldout, args.sizes, args.frames, args.repeat)
        return
    x, r = _pbf_frame(args.particles)
    net = MetaballNet(args.weights)
    launch = Launcher("cpu")
    d = DatasetConfig()

    def ellipsoids(cam):
        """What the renderer hands the method: the ellipsoids of the particles ``cam`` sees."""
        if not net.config.anisotropic:
            return None
        return particle_ellipsoids(x, r, d, launch, "cpu", seen_kernels(x, r, d, cam, launch, "cpu")[0])

    print(f"metaball method, {len(x)} particles (r = {1000 * r:.1f} mm), shipped generator "
          f"({sum(p.numel() for p in net.generator.parameters()) / 1e6:.2f} M parameters), "
          f"{torch.get_num_threads()} torch threads")
    kind = net.config.input
    print(f"{'size':>6} {'working':>9} {'ellipsoids ms':>14} {kind + ' ms':>11} {'generator ms':>13} {'method ms':>10} "
          f"{'ray march ms':>13} {'march/method':>13}")
    for size in args.sizes:
        cam = _camera_for(x, size)
        ell = ellipsoids(cam)
        view = net.view(x, r, cam, ell)
        inputs = view.inputs(kind, launch)
        t_ell = _median_ms(lambda c=cam: ellipsoids(c), args.repeat) if ell is not None else 0.0
        t_inputs = _median_ms(lambda v=view: v.inputs(kind, launch), args.repeat)
        t_net = _median_ms(lambda c=inputs: predict(net.generator, c), args.repeat)
        t_method = _median_ms(lambda c=cam: net.gbuffers(x, r, c, launch, ellipsoids(c)), args.repeat)
        t_march = float("nan") if args.no_march else _median_ms(lambda v=view: v.targets(launch, own_size=True), 1)
        working = f"{view.camera.width}x{view.camera.height}"
        print(f"{size:>6} {working:>9} {t_ell:>14.1f} {t_inputs:>11.1f} {t_net:>13.1f} {t_method:>10.1f} "
              f"{t_march:>13.0f} {t_march / t_method:>12.1f}x")
    launch.close()


if __name__ == "__main__":
    main()
