"""The package's modules import each other without cycles (module-level and function-level imports
alike): the stages at the core, the command modules on top, none of them importing back."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {"nanogs_warp": ROOT / "nanogs_warp", "nanogs_warp.kernels": ROOT / "kernels"}


def package_modules() -> dict[str, Path]:
    modules = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = [package, *path.relative_to(folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            submodules = {f"{target}.{a.name}" for a in node.names} & modules.keys()
            found |= submodules
            if len(submodules) < len(node.names):  # names from the module itself
                found.add(target)
    return {m for m in found if m in modules and m != name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = package_modules()
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def test_no_import_cycles():
    graph = import_graph()
    assert "nanogs_warp.cli_batch" in graph and "nanogs_warp.kernels.merge" in graph
    assert cycles(graph) == []


def test_the_checker_finds_a_cycle():
    graph = import_graph()
    graph["nanogs_warp.pipeline"] = graph["nanogs_warp.pipeline"] | {"nanogs_warp.cli"}
    assert any("nanogs_warp.pipeline" in c and "nanogs_warp.cli" in c for c in cycles(graph))
    # the command line depends on the stages, the stages never on it
    assert "nanogs_warp.pipeline" in import_graph()["nanogs_warp.cli"]


def test_kernels_import_no_host_code():
    for name, deps in import_graph().items():
        if name.startswith("nanogs_warp.kernels"):
            assert all(d.startswith("nanogs_warp.kernels") for d in deps), (name, deps)
