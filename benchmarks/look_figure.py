"""Before/after picture of the default look: the same frames rendered by two checkouts of the code.

Each checkout renders the dam break's ``--frames`` (from a cached simulation) with its own
default render settings at 512x512, method refined, through ``pipeline.renderer.SequenceRenderer``
in a subprocess; the previews are tiled old above new with labels.

    git archive <old commit> | tar -x -C /tmp/before
    .venv/bin/python benchmarks/look_figure.py --before /tmp/before --sim data/simulate/dam_break-<key> \\
        --frames 1 40 --out docs/images/look_before_after.png
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]

RENDER = """
import dataclasses, sys
from pathlib import Path
sys.path.insert(0, {root!r})
from pipeline.camera import camera_for_frame
from pipeline.config_files import load
from pipeline.frames import load_frame
from pipeline.model import SHIPPED_WEIGHTS
from pipeline.model.inference import load_weights
from pipeline.renderer import SequenceRenderer
from pipeline.shading.background import Surroundings

loaded = load({root!r} + "/configs/default.yaml", only_scene="dam_break")
p = dataclasses.replace(loaded.config.render, width=512, height=512, method="refined", comparison=False)
config = dataclasses.replace(loaded.config, render=p)
scene = loaded.scenes["dam_break"]
refiner, _ = load_weights(SHIPPED_WEIGHTS, "cpu")
frames = {frames!r}
with SequenceRenderer(Path({out!r}), "look", Surroundings.of_scene(scene), config, "cpu", refiner) as renderer:
    renderer.render(frames, lambda f: load_frame(Path({sim!r}) / f"frame_{{f:04d}}.npz"), {radius!r},
                    lambda i: camera_for_frame(scene.cameras, "static", i, len(frames), 512, 512))
"""


def render_previews(root: Path, sim: Path, frames: list[int], radius: float, out: Path) -> list[np.ndarray]:
    """The preview PNGs of ``frames`` rendered by the code at ``root``."""
    script = RENDER.format(root=str(root), frames=frames, out=str(out), sim=str(sim.resolve()), radius=radius)
    subprocess.run([sys.executable, "-c", script], cwd=root, check=True)
    return [np.asarray(Image.open(out / "preview" / f"frame_{f:04d}.png").convert("RGB")) for f in frames]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", type=Path, required=True, help="checkout of the old code")
    ap.add_argument("--after", type=Path, default=ROOT, help="checkout of the new code (default: this one)")
    ap.add_argument("--sim", type=Path, required=True, help="cached dam-break simulation folder")
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 40])
    ap.add_argument("--radius", type=float, default=0.0125, help="particle radius of the simulation (m)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "look_before_after.png")
    args = ap.parse_args()
    from pipeline.media import label

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, root in (("before", args.before), ("after", args.after)):
            tiles = render_previews(root.resolve(), args.sim, args.frames, args.radius, Path(tmp) / name)
            rows.append(np.concatenate([label(t, f"{name}: frame {f}") for t, f in zip(tiles, args.frames,
                                                                                     strict=True)], axis=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out)
    print(args.out)


if __name__ == "__main__":
    main()
