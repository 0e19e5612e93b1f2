"""SPlisHSPlasH (Bender et al., the reference research SPH library) on the benchmark's dam break.

Runs SPlisHSPlasH's own PBF (Macklin & Mueller 2013; exactly 4 iterations: min = max = 4) or
DFSPH (Bender & Koschier 2017; its default error bounds, divergence solver on) through the
``pysplishsplash`` wheel, on the same container and block as ``dam_break.py``: particle radius r,
support 4r, fixed time step 1/120 s (no CFL), XSPH 0.01 and vorticity confinement 0.005 (SPlisHSPlasH
adds them as accelerations after the solve), volume-map walls (Bender et al. 2019) and its own
block filling (a few percent fewer particles than the project's lattice) and kernels (cubic spline).

The wheel bundles libGLX / libGLdispatch / libOpenGL under renamed files (``pysplishsplash.libs``)
while its bundled libGLU pulls in the system's libGL, which loads the system's libGLdispatch too:
two GL dispatch tables in one process, and the import dies with a segmentation fault. Before the
import, ``gl_safe_module_dir`` builds a folder in the user cache that mirrors the installed module
(a link to the extension) next to a ``pysplishsplash.libs`` whose GL libraries are links to the
system's (the rest link to the bundled files). The extension finds its libraries through
``$ORIGIN``, which is the mirror's folder, so every GL library is loaded once. Nothing installed is
modified; without a system libGL the import goes ahead as shipped.

    .venv/bin/python benchmarks/peers/splishsplash.py --method pbf --particles 50000 --steps 40 --threads 2
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import importlib.util
import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import dam_break  # noqa: E402

# Bundled libraries of the GL family, renamed by auditwheel as <name>-<hash>.so.<version>.
GL_LIBRARY = re.compile(r"^(lib(?:GL|OpenGL)[A-Za-z]*)-[0-9a-f]{8}(\.so\.\d+)")
BOX_OBJ = """v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1
f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 4 8 7\nf 4 7 3\nf 1 5 8\nf 1 8 4\nf 2 3 7\nf 2 7 6
"""
METHODS = {"pbf": 2, "dfsph": 4}
"""Scene-file simulationMethod of each solver."""


def cache_dir() -> Path:
    """This peer's folder in the user cache."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "deep-ssfr" / "splishsplash"


def system_library(soname: str) -> str | None:
    """Path of the system's library ``soname`` (e.g. libGLX.so.0), or None when it has none."""
    try:
        ctypes.CDLL(soname)
    except OSError:
        return None
    with open("/proc/self/maps") as maps:
        for line in maps:
            path = line.split(maxsplit=5)[-1].strip()
            if os.path.basename(path).startswith(soname) and "pysplishsplash" not in path:
                return path
    return None


def gl_safe_module_dir() -> Path | None:
    """A folder to put first on sys.path so that ``import pysplishsplash`` shares the system's GL
    libraries (see the module docstring); None when no system GL library is installed."""
    spec = importlib.util.find_spec("pysplishsplash")
    if spec is None or spec.origin is None:
        raise ImportError("the SPlisHSPlasH peer needs pysplishsplash: pip install -e '.[bench]'")
    extension = Path(spec.origin).resolve()
    bundled = extension.parent / "pysplishsplash.libs"
    links = {}
    for lib in sorted(bundled.iterdir()) if bundled.is_dir() else []:
        match = GL_LIBRARY.match(lib.name)
        target = system_library(match.group(1) + match.group(2)) if match else None
        links[lib.name] = target or str(lib)
    if all(target.startswith(str(bundled)) for target in links.values()):
        return None
    key = hashlib.sha256(json.dumps([str(extension), links]).encode()).hexdigest()[:12]
    cache = cache_dir() / "gl"
    folder = cache / key
    if not (folder / extension.name).exists():
        # build in a private folder, then rename: concurrent runs never see a half-made mirror
        cache.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(dir=cache))
        (staging / "pysplishsplash.libs").mkdir()
        (staging / extension.name).symlink_to(extension)
        for name, target in links.items():
            (staging / "pysplishsplash.libs" / name).symlink_to(target)
        try:
            staging.rename(folder)
        except OSError:  # another run made it first
            shutil.rmtree(staging, ignore_errors=True)
    return folder


def import_pysplishsplash():
    """``import pysplishsplash`` without the GL clash."""
    folder = gl_safe_module_dir()
    if folder is not None:
        sys.path.insert(0, str(folder))
    import pysplishsplash

    return pysplishsplash


def scene_file(method: str, particles: int) -> Path:
    """The dam break as a SPlisHSPlasH scene file (and its container mesh) in a folder of the user
    cache named by the scene's hash, where SPlisHSPlasH also caches its volume map (building it
    takes 7 s at 50k particles and grows with the resolution)."""
    radius = dam_break.radius_for(particles)
    p = dam_break.params(particles)
    support = p.kernel_radius_factor * radius
    domain = dam_break.DOMAIN_HI
    configuration = {
        "particleRadius": radius, "timeStepSize": 1.0 / (p.fps * p.substeps), "cflMethod": 0,
        "simulationMethod": METHODS[method], "gravitation": list(p.gravity), "boundaryHandlingMethod": 2,
        "enableZSort": True, "numberOfStepsPerRenderUpdate": 1, "stopAt": -1, "pause": False,
        "enablePartioExport": False, "enableVTKExport": False, "enableRigidBodyExport": False,
        "enableStateExport": False,
    }
    scene = {
        "Configuration": configuration,
        # XSPH is its own module in SPlisHSPlasH 2.19 (viscosityMethod 2 is an implicit solver there);
        # ``configure`` sets the coefficients again through the API
        "Materials": [{"id": "Fluid", "density0": p.rest_density, "viscosityMethod": 0, "xsph": p.xsph_viscosity,
                       "xsphBoundary": 0.0, "vorticityMethod": 2, "vorticity": p.vorticity_epsilon}],
        "RigidBodies": [{"geometryFile": "box.obj", "translation": [0.0, 0.0, 0.0],
                         "scale": list(domain), "isDynamic": False, "isWall": True, "mapInvert": True,
                         "mapThickness": 0.0, "color": [0.1, 0.4, 0.6, 1.0],
                         # about one volume-map cell per support radius
                         "mapResolution": [max(8, math.ceil(e / support)) for e in domain]}],
        "FluidBlocks": [{"id": "Fluid", "denseMode": 0, "start": [0.0, 0.0, 0.0], "end": list(dam_break.BLOCK_HI)}],
    }
    text = json.dumps(scene, indent=1)
    folder = cache_dir() / "scenes" / hashlib.sha256((text + BOX_OBJ).encode()).hexdigest()[:12]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "box.obj").write_text(BOX_OBJ)
    (folder / "dam_break.json").write_text(text)
    return folder / "dam_break.json"


def configure(sim, method: str) -> None:
    """Set the solver's iterations and the non-pressure forces through the API: the scene file's
    values for these do not reach the 2.19 objects (they read back as the defaults)."""
    p = dam_break.params(1)
    step, fluid = sim.getTimeStep(), sim.getFluidModel(0)
    if method == "pbf":
        step.setValueUInt(step.MIN_ITERATIONS, p.iterations)
        step.setValueUInt(step.MAX_ITERATIONS, p.iterations)
    xsph, vorticity = fluid.getXSPH(), fluid.getVorticityBase()
    xsph.setValueFloat(xsph.FLUID_COEFFICIENT, p.xsph_viscosity)
    xsph.setValueFloat(xsph.BOUNDARY_COEFFICIENT, 0.0)
    vorticity.setValueFloat(vorticity.VORTICITY_COEFFICIENT, p.vorticity_epsilon)


def settings(sph, sim) -> dict:
    """The settings as SPlisHSPlasH reports them after the run, and its mean solver iterations."""
    step, fluid = sim.getTimeStep(), sim.getFluidModel(0)
    xsph, vorticity = fluid.getXSPH(), fluid.getVorticityBase()
    counts = {name: c.sum / max(1, c.numberOfCalls) for name, c in sph.Utilities.Counting.m_averageCounts.items()}
    return {"min_iterations": step.getValueUInt(step.MIN_ITERATIONS),
            "max_iterations": step.getValueUInt(step.MAX_ITERATIONS),
            "max_error_percent": round(step.getValueFloat(step.MAX_ERROR), 6),
            "mean_iterations": {k: round(v, 2) for k, v in counts.items() if "iterations" in k.lower()},
            "xsph": round(xsph.getValueFloat(xsph.FLUID_COEFFICIENT), 6),
            "vorticity_confinement": round(vorticity.getValueFloat(vorticity.VORTICITY_COEFFICIENT), 6),
            "viscosity_method": fluid.getValueInt(fluid.VISCOSITY_METHOD),
            "vorticity_method": fluid.getValueInt(fluid.VORTICITY_METHOD),
            "cfl_method": sim.getValueInt(sim.CFL_METHOD)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", choices=sorted(METHODS), default="pbf")
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--warmup", type=int, default=dam_break.WARMUP_STEPS, help="untimed steps first")
    parser.add_argument("--threads", type=int, default=0, help="OpenMP threads (0: one per core)")
    args = parser.parse_args()
    threads = args.threads or os.cpu_count() or 1
    os.environ["OMP_NUM_THREADS"] = str(threads)  # read when the bundled libgomp loads
    sph = import_pysplishsplash()
    with tempfile.TemporaryDirectory(prefix="splishsplash-") as output:
        scene = scene_file(args.method, args.particles)
        before = dam_break.resident_bytes()
        base = sph.Exec.SimulatorBase()
        base.init(sceneFile=str(scene), useGui=False, initialPause=False, useCache=True, outputDir=output,
                  stopAt=-1.0)
        base.initSimulation()
        sim = sph.Simulation.getCurrent()
        fluid = sim.getFluidModel(0)
        dt = sph.TimeManager.getCurrent().getTimeStepSize()
        configure(sim, args.method)
        args.warmup = max(1, args.warmup)  # the first stamp ends the warm-up
        total = args.warmup + args.steps
        # runSimulation does the deferred set-up (volume maps) and steps until stopAt; the time-step
        # callback stamps the end of every step
        stamps: list[float] = []
        base.setTimeStepCB(lambda: stamps.append(time.perf_counter()))
        base.setValueFloat(base.STOP_AT, (total - 0.5) * dt)
        base.runSimulation()
        memory = dam_break.resident_bytes() - before
        timed = stamps[args.warmup - 1:]
        if len(timed) != args.steps + 1:
            raise RuntimeError(f"SPlisHSPlasH ran {len(stamps)} steps, not {total}")
        ends = [(b, min(b + dam_break.BLOCK_STEPS, args.steps)) for b in range(0, args.steps, dam_break.BLOCK_STEPS)]
        rates = [(e - b) / (timed[e] - timed[b]) for b, e in ends]
        seconds = timed[-1] - timed[0]
        extra = {"pysplishsplash": "2.19", "radius": sim.getParticleRadius(), "support": sim.getSupportRadius(),
                 "time_step": dt, **settings(sph, sim)}
        result = dam_break.Measurement(f"SPlisHSPlasH {args.method.upper()}", fluid.numActiveParticles(),
                                       args.steps, seconds, rates, memory, threads, extra)
        print(result.to_json(), flush=True)
        # the library's exit (its timing tables, its threads) is of no interest here
        os._exit(0)


if __name__ == "__main__":
    main()
