"""
The package's layout: its import map has no cycle (imports inside functions and TYPE_CHECKING blocks included), the
root holds the algorithm, and the algorithm loads no env adapter it does not use.
"""

import ast
import pathlib
import subprocess
import sys

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
    assert (
        "sb3_cgac.cgac" in edges["sb3_cgac"] and "sb3_cgac.common.obs_rows" in edges["sb3_cgac.collection"]
    )  # the walk works
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


# The package root: the algorithm's modules, the public entry points and threads.py; infrastructure lives in common/,
# env adapters and wrappers in vec_env/, tools in their subpackages
ROOT_MODULES = {
    "__init__",
    "buffers",
    "callbacks",
    "cgac",
    "collection",
    "critics",
    "enjoy",
    "hyperparameters",
    "losses",
    "policies",
    "return_scale",
    "threads",
    "torch_layers",
    "train",
    "window_algorithm",
}


def test_package_root_holds_the_algorithm():
    assert {path.stem for path in PACKAGE.glob("*.py")} == ROOT_MODULES
    assert {"common", "compare", "export", "rsl_rl", "vec_env", "zoo"} <= {path.name for path in PACKAGE.iterdir()}


def test_algorithm_loads_no_env_adapter():
    # The algorithm imports the torch-native adapter's module, not the adapters' package: envpool, gymnasium's vector
    # envs, Playground and mjlab load only with their backend
    code = "import sys, sb3_cgac.cgac; print(sorted(m for m in sys.modules if m.startswith('sb3_cgac.vec_env')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == str(["sb3_cgac.vec_env", "sb3_cgac.vec_env.episodes", "sb3_cgac.vec_env.torch_vec_env"])
