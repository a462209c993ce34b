"""The package's import map has no cycle (imports inside functions and TYPE_CHECKING blocks included)."""

import ast
import pathlib

PACKAGE = pathlib.Path(__file__).parents[1] / "sb3_cgac"


def import_map() -> dict[str, set[str]]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
        modules[name] = path
    edges: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sb3_cgac"):
                targets = [node.module, *(f"{node.module}.{alias.name}" for alias in node.names)]
            elif isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            edges[name] |= {target for target in targets if target in modules and target != name}
    return edges


def test_import_map_has_no_cycle():
    edges = import_map()
    assert "sb3_cgac.cgac" in edges["sb3_cgac"] and "sb3_cgac.obs_rows" in edges["sb3_cgac.collection"]  # the walk works
    visiting: list[str] = []
    done: set[str] = set()

    def visit(module: str) -> None:
        if module in visiting:
            raise AssertionError("import cycle: " + " -> ".join([*visiting[visiting.index(module) :], module]))
        if module in done:
            return
        visiting.append(module)
        for imported in sorted(edges[module]):
            visit(imported)
        visiting.pop()
        done.add(module)

    for module in sorted(edges):
        visit(module)
