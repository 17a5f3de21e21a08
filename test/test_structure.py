"""The house rules a newcomer relies on: no import cycles in the core, no module or function
too long to read, the core free of ROS, the planners' physics apart from the simulator."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "src"
PACKAGES = ["afm_ros", "afm_bringup", "afm_driver", "afm_imaging", "afm_localization",
            "afm_planning", "afm_manipulation", "afm_viewer"]  # fmt: skip
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 120


def python_files():
    yield from sorted(CORE.rglob("*.py"))
    for package in PACKAGES:
        yield from sorted((ROOT / package / package).rglob("*.py"))


def module_name(path: Path) -> str:
    parts = list(path.relative_to(CORE).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def core_imports() -> dict[str, set[str]]:
    """Core module -> the core modules it imports (a submodule imported from a package counts
    as the submodule, not the package)."""
    files = {module_name(p): p for p in CORE.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names if a.name in files}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module
                submodules = {f"{target}.{a.name}" for a in node.names} & set(files)
                edges |= submodules
                if target in files and len(submodules) < len(node.names):
                    edges.add(target)
        graph[name] = edges
    return graph


def test_no_import_cycle_in_the_core():
    graph = core_imports()
    state: dict[str, int] = {}
    cycles = []

    def visit(name, stack):
        state[name] = 1
        for other in sorted(graph[name]):
            if state.get(other) == 1:
                cycles.append(stack[stack.index(other) :] + [other])
            elif other not in state:
                visit(other, stack + [other])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_no_module_or_function_too_long_to_read():
    too_long = []
    for path in python_files():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(
                        f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {length}"
                    )
    assert not too_long, "\n".join(too_long)


@pytest.mark.parametrize(
    "module, forbidden",
    [
        ("afm_core", "rclpy"),  # the core never imports ROS (checked over every core module)
        ("afm_core.physics", "afm_core.sim"),  # the planners' model without the simulator
    ],
)
def test_import_boundaries(module, forbidden):
    names = sorted(module_name(p) for p in CORE.rglob("*.py") if module_name(p).startswith(module))
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        f"bad = sorted(m for m in sys.modules if m == {forbidden!r} or "
        f"m.startswith({forbidden!r} + '.'))\n"
        "print(' '.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"
