"""The layers hold: imports only go down (algorithms <- stages <- orchestration), in a circle
nowhere. Every import statement counts, the ones inside functions too."""
from __future__ import annotations

import ast

from conftest import ROOT

PACKAGES = ("pipeline", "solver", "surfacing")


def module_name(path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_imports() -> dict[str, set[str]]:
    """module -> the project modules it imports (`from pkg import name` counts as pkg.name
    when that is a module, else as pkg)."""
    files = {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            deps |= {n for n in names if n in files and n != mod}
        graph[mod] = deps
    return graph


def test_the_walker_sees_imports():
    """The walker itself: it finds imports of all three kinds (a check that cannot miss)."""
    g = project_imports()
    assert "pipeline.cache" in g["pipeline.formats"]                 # relative, from-import
    assert "solver.kernels" in g["surfacing.splat"]                  # absolute, from-import of a module
    assert "pipeline.stages.render" not in g["pipeline.cli"]         # loaded by name, not imported
    assert "pipeline.meshes" in g["pipeline.spec"]                   # inside a function


def test_libraries_do_not_import_the_pipeline():
    for mod, deps in project_imports().items():
        if mod.startswith(("solver", "surfacing")):
            up = sorted(d for d in deps if d.startswith("pipeline"))
            assert not up, f"{mod} imports {up}: solver/ and surfacing/ are libraries below pipeline/"
        if mod.startswith("solver"):
            side = sorted(d for d in deps if d.startswith("surfacing"))
            assert not side, f"{mod} imports {side}: the solver does not depend on the surfacer"


def test_no_import_circles():
    graph = project_imports()
    state: dict[str, int] = {}          # 1: on the current path, 2: done
    path: list[str] = []

    def visit(mod):
        state[mod] = 1
        path.append(mod)
        for dep in sorted(graph[mod]):
            if state.get(dep) == 1:
                circle = path[path.index(dep):] + [dep]
                raise AssertionError("import circle: " + " -> ".join(circle))
            if dep not in state:
                visit(dep)
        path.pop()
        state[mod] = 2

    for mod in sorted(graph):
        if mod not in state:
            visit(mod)
