"""The package's modules import each other without cycles (module-level and function-level imports
alike), and in one direction: the kernels import no host code, the stages at the core import none of
the subpackages, io/ none of eval/, refinement/, batch/ or cli/, and so on up to cli/, which nothing
imports."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {"nanogs_warp": ROOT / "nanogs_warp", "nanogs_warp.kernels": ROOT / "kernels"}

# Lowest first: a module may import its own layer and those below it, never one above.
LAYERS = ["kernels", "core", "io", "eval", "refinement", "batch", "cli"]
SUBPACKAGES = ("io", "eval", "refinement", "batch", "cli")


def package_modules() -> dict[str, Path]:
    modules = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = [package, *path.relative_to(folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def _is_type_checking(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST, type_checking: bool):
    """Every Import/ImportFrom node, module-level and inside functions; those under
    ``if TYPE_CHECKING:`` (which never run) only when ``type_checking``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        for child in ast.iter_child_nodes(node):
            if type_checking or not _is_type_checking(child):
                stack.append(child)


def imports_of(name: str, path: Path, modules: dict[str, Path], type_checking: bool = True) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in _import_nodes(ast.parse(path.read_text(encoding="utf-8")), type_checking):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        else:
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


def import_graph(type_checking: bool = True) -> dict[str, set[str]]:
    modules = package_modules()
    return {name: imports_of(name, path, modules, type_checking) for name, path in modules.items()}


def layer_of(module: str) -> str:
    """``kernels``, one of SUBPACKAGES, or ``core`` (the package's top-level modules, data/ and the
    package itself, whose names load lazily); ``python -m nanogs_warp`` is the command line."""
    if module == "nanogs_warp.__main__":
        return "cli"
    parts = module.split(".")
    if len(parts) > 1 and parts[1] in ("kernels", *SUBPACKAGES):
        return parts[1]
    return "core"


def test_the_walk_sees_every_subpackage():
    graph = import_graph()
    assert len(graph) > 70 and sum(len(deps) for deps in graph.values()) > 150
    for layer in LAYERS:
        members = [m for m in graph if layer_of(m) == layer]
        assert len(members) >= 5, (layer, members)
    for module in ("nanogs_warp.cli.batch", "nanogs_warp.cli.app", "nanogs_warp.io.ply", "nanogs_warp.eval.render",
                   "nanogs_warp.refinement.render_grad", "nanogs_warp.batch.work", "nanogs_warp.kernels.merge"):
        assert module in graph, module
    # relative imports resolve across subpackages, function-level ones included
    assert {"nanogs_warp.pipeline", "nanogs_warp.refinement.refine", "nanogs_warp.io"} <= graph["nanogs_warp.cli.app"]
    assert "nanogs_warp.eval.render" in graph["nanogs_warp.refinement.render_grad"]
    assert "nanogs_warp.kernels.merge" in graph["nanogs_warp.operators"]


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_the_checker_finds_a_cycle():
    graph = import_graph()
    graph["nanogs_warp.pipeline"] = graph["nanogs_warp.pipeline"] | {"nanogs_warp.cli.app"}
    assert any("nanogs_warp.pipeline" in c and "nanogs_warp.cli.app" in c for c in cycles(graph))
    # the command line depends on the stages, the stages never on it
    assert "nanogs_warp.pipeline" in import_graph()["nanogs_warp.cli.app"]


def _upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    return sorted((m, d) for m, deps in graph.items() for d in deps if rank[layer_of(d)] > rank[layer_of(m)])


def test_layers_import_only_downward():
    """Imports that run (not those under ``if TYPE_CHECKING:``) point down the layers."""
    assert _upward_imports(import_graph(type_checking=False)) == []


def test_the_layer_check_finds_an_upward_import():
    graph = import_graph(type_checking=False)
    graph["nanogs_warp.io.ply"] = graph["nanogs_warp.io.ply"] | {"nanogs_warp.eval.render"}
    assert _upward_imports(graph) == [("nanogs_warp.io.ply", "nanogs_warp.eval.render")]
    # type-only imports are not counted: the splat set names its layout's type only for checkers
    assert "nanogs_warp.io.ply_layout" in import_graph()["nanogs_warp.splats"]
    assert "nanogs_warp.io.ply_layout" not in import_graph(type_checking=False)["nanogs_warp.splats"]


def test_kernels_import_no_host_code():
    for name, deps in import_graph().items():
        if name.startswith("nanogs_warp.kernels"):
            assert all(d.startswith("nanogs_warp.kernels") for d in deps), (name, deps)
