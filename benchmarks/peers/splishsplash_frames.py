"""Training frames from another simulator: SPlisHSPlasH 2.19 (DFSPH) on scenes of the project's own.

The refiner must not only know the project's PBF: users bring SPH frames whose particles sit
differently (DFSPH keeps the density within 0.01%, particles are sampled by SPlisHSPlasH's own
block filling, walls are volume maps). This runs SPlisHSPlasH (MIT) through the
``pysplishsplash`` wheel (the ``bench`` extra; its GL clash is handled by ``splishsplash``) on
scenes defined here, unlike the held-out SPlisHSPlasH frames of ``../shared/data/particles`` (a
bunny, a dam break and a double dam break from splashsurf's test data), and writes each frame as
SPlisHSPlasH's own Partio BGEO export, which the imported scenes ``configs/scenes/sph_*.yaml``
read, and one held-out sequence (``sph_heldout_columns``, evaluated with its per-pixel temporal
error, never trained on):

    .venv/bin/pip install -e '.[bench]'
    .venv/bin/python benchmarks/peers/splishsplash_frames.py [--scenes sph_pool_drop sph_slosh] [--out data/external]

Writes ``<out>/splishsplash/<scene>/ParticleData_Fluid_<n>.bgeo`` (n = 1 ...) and ``done.json``;
a scene whose ``done.json`` exists is skipped. ``configs/generalize.yaml`` trains on them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from splishsplash import BOX_OBJ, import_pysplishsplash  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

SCENES = {
    # a slab dropped off-centre into a pool, particles of 15 mm (the project's PBF scenes use 12.5 mm)
    "sph_pool_drop": {
        "radius": 0.015, "domain": [2.0, 1.2, 1.2],
        "blocks": [([0.0, 0.0, 0.0], [2.0, 0.2, 1.2], [0.0, 0.0, 0.0]),
                   ([0.55, 0.5, 0.35], [1.0, 0.85, 0.8], [0.0, -1.0, 0.0])],
    },
    # a block thrown sideways across a long shallow pool: a breaking wave, particles of 20 mm
    "sph_slosh": {
        "radius": 0.02, "domain": [2.2, 1.0, 1.0],
        "blocks": [([0.0, 0.0, 0.0], [2.2, 0.2, 1.0], [0.0, 0.0, 0.0]),
                   ([0.1, 0.35, 0.3], [0.5, 0.75, 0.7], [2.5, 0.5, 0.0])],
    },
    # held out, never trained on (configs/generalize.yaml): two columns at opposite corners collapse
    # into a shallow basin and meet in the middle, particles of 12.5 mm
    "sph_heldout_columns": {
        "radius": 0.0125, "domain": [1.6, 1.0, 1.0], "frames": 48,
        "blocks": [([0.0, 0.0, 0.0], [1.6, 0.1, 1.0], [0.0, 0.0, 0.0]),
                   ([0.05, 0.1, 0.05], [0.35, 0.6, 0.45], [0.0, 0.0, 0.0]),
                   ([1.25, 0.1, 0.55], [1.55, 0.6, 0.95], [0.0, 0.0, 0.0])],
    },
}
FPS = 30.0


def scene_json(name: str, frames: int) -> dict:
    """A SPlisHSPlasH scene file: DFSPH, volume-map box walls, the scene's blocks and emitters, a
    Partio export at ``FPS`` frames a second."""
    s = SCENES[name]
    r = s["radius"]
    support = 4.0 * r
    config = {"particleRadius": r, "timeStepSize": 0.002, "cflMethod": 1, "cflFactor": 0.5,
              "cflMaxTimeStepSize": 0.005, "simulationMethod": 4, "gravitation": [0.0, -9.81, 0.0],
              "boundaryHandlingMethod": 2, "enableZSort": True, "stopAt": frames / FPS, "pause": False,
              "enablePartioExport": True, "dataExportFPS": FPS, "particleAttributes": "velocity",
              "enableVTKExport": False, "enableRigidBodyExport": False, "enableStateExport": False}
    material = {"id": "Fluid", "density0": 1000.0, "viscosityMethod": 0, "xsph": 0.01, "xsphBoundary": 0.0,
                "vorticityMethod": 2, "vorticity": 0.005}
    scene = {"Configuration": config, "Materials": [material],
             "RigidBodies": [{"geometryFile": "box.obj", "translation": [0.0, 0.0, 0.0], "scale": s["domain"],
                              "isDynamic": False, "isWall": True, "mapInvert": True, "mapThickness": 0.0,
                              "mapResolution": [max(8, math.ceil(e / support)) for e in s["domain"]]}],
             "FluidBlocks": [{"id": "Fluid", "denseMode": 0, "start": lo, "end": hi, "initialVelocity": v}
                             for lo, hi, v in s["blocks"]]}
    return scene


def simulate(name: str, frames: int, out: Path) -> None:
    """Run one scene and move its BGEO frames into ``out/<name>``."""
    target = out / name
    if (target / "done.json").exists():
        print(f"{name}: done already ({target})")
        return
    sph = import_pysplishsplash()
    with tempfile.TemporaryDirectory(prefix="splishsplash-") as work:
        folder = Path(work)
        (folder / "box.obj").write_text(BOX_OBJ)
        (folder / "scene.json").write_text(json.dumps(scene_json(name, frames), indent=1))
        start = time.perf_counter()
        base = sph.Exec.SimulatorBase()
        base.init(sceneFile=str(folder / "scene.json"), useGui=False, initialPause=False, useCache=False,
                  outputDir=str(folder / "output"), stopAt=frames / FPS)
        base.initSimulation()
        base.runSimulation()
        files = sorted((folder / "output" / "partio").glob("ParticleData_Fluid_*.bgeo"),
                       key=lambda p: int(p.stem.rsplit("_", 1)[1]))
        if len(files) < frames:
            raise RuntimeError(f"{name}: SPlisHSPlasH wrote {len(files)} frames, not {frames}")
        tmp = out / f".{name}.tmp-{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for i, f in enumerate(files[:frames], start=1):
            shutil.move(str(f), tmp / f"ParticleData_Fluid_{i}.bgeo")
        seconds = time.perf_counter() - start
        (tmp / "done.json").write_text(json.dumps({"scene": scene_json(name, frames), "frames": frames,
                                                   "seconds": round(seconds, 1), "simulator": "SPlisHSPlasH 2.19"}))
        shutil.rmtree(target, ignore_errors=True)
        tmp.rename(target)
        print(f"{name}: {frames} frames in {seconds:.0f} s -> {target}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--frames", type=int, default=100, help="frames of a scene that names none")
    parser.add_argument("--out", type=Path, default=ROOT / "data" / "external")
    parser.add_argument("--threads", type=int, default=0, help="OpenMP threads (0: one per core)")
    args = parser.parse_args()
    os.environ["OMP_NUM_THREADS"] = str(args.threads or os.cpu_count() or 1)
    if len(args.scenes) > 1:
        # one process a scene: a second SimulatorBase in one process exports no frames
        for name in args.scenes:
            subprocess.run([sys.executable, __file__, "--scenes", name, "--frames", str(args.frames),
                            "--out", str(args.out), "--threads", str(args.threads)], check=True)
    else:
        simulate(args.scenes[0], SCENES[args.scenes[0]].get("frames", args.frames), args.out / "splishsplash")
    sys.stdout.flush()
    os._exit(0)  # the library's exit (timing tables, threads) is of no interest


if __name__ == "__main__":
    main()
