"""The house rules a newcomer relies on: no import cycles, no import from a higher layer."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.conftest import ROOT

# Low to high; a module may import its own layer or lower ones. The longest matching prefix decides.
LAYERS = (
    ("foundation", ("pipeline", "pipeline.config", "pipeline.config_files", "pipeline.cache", "pipeline.fencing",
                    "pipeline.sph",
                    "pipeline.vectors", "pipeline.timing", "pipeline.device", "pipeline.resources", "pipeline.exr",
                    "pipeline.frames", "pipeline.particles", "pipeline.camera", "pipeline.writer", "pipeline.media",
                    "pipeline.profiling", "pipeline.plots", "pipeline.executor", "pipeline.parallel", "pipeline.gang",
                    "pipeline.ellipsoids")),
    ("kernels", ("pipeline.sim", "pipeline.screen", "pipeline.surface", "pipeline.shading", "pipeline.masks",
                 "pipeline.metrics", "pipeline.metaball.kernels")),
    ("methods", ("pipeline.model", "pipeline.metaball", "pipeline.views", "pipeline.methods", "pipeline.dataset")),
    ("renderer", ("pipeline.renderer", "pipeline.evaluate")),
    ("stages", ("stages",)),
)


def _modules() -> dict[str, Path]:
    found = {}
    for path in [*ROOT.glob("pipeline/**/*.py"), *ROOT.glob("stages/*.py")]:
        parts = path.relative_to(ROOT).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _imports(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Every project module each module imports, lazy ones included."""
    def owner(name: str) -> str:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: from the package, node.level - 1 up
                    up = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join([*up, *filter(None, [base])])
                targets = [base, *(f"{base}.{a.name}" for a in node.names)]
            else:
                continue
            found |= {owner(t) for t in targets} - {"", name}
        graph[name] = found
    return graph


def _layer(module: str) -> int:
    best = max(((len(prefix), i) for i, (_, prefixes) in enumerate(LAYERS) for prefix in prefixes
                if module == prefix or module.startswith(prefix + ".")), default=None)
    assert best is not None, f"{module} is in no layer: add it to LAYERS"
    return best[1]


def test_no_module_imports_one_from_a_higher_layer():
    upward = [f"{a} ({LAYERS[_layer(a)][0]}) -> {b} ({LAYERS[_layer(b)][0]})"
              for a, targets in _imports(_modules()).items() for b in sorted(targets) if _layer(b) > _layer(a)]
    assert not upward, "\n".join(upward)


def test_the_import_graph_has_no_cycle():
    graph = _imports(_modules())
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> None:
        if node in path:
            raise AssertionError("import cycle: " + " -> ".join([*path[path.index(node):], node]))
        if node in done:
            return
        for target in sorted(graph[node]):
            visit(target, [*path, node])
        done.add(node)

    for node in sorted(graph):
        visit(node, [])


def test_no_source_file_is_over_800_lines():
    """A file a reader can hold in mind: past 800 lines a module holds more than one idea."""
    long = [f"{p.relative_to(ROOT)}: {n} lines" for folder in ("pipeline", "stages", "benchmarks", "tests")
            for p in sorted((ROOT / folder).rglob("*.py")) if (n := len(p.read_text().splitlines())) > 800]
    assert not long, "\n".join(long)
