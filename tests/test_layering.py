"""The layout's import rules (DESIGN.md, "Layout"), read from the source: every import,
at module level or inside a function."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"pipeline", "sim", "hardware", "eval"}
#: The command line's folder: the one place in flowerpose/ that may use every package.
COMMAND_LINE = ROOT / "flowerpose" / "cli"


def _imports(path: Path) -> set[str]:
    """The packages of PACKAGES a module imports."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        for name in names:
            parts = name.split(".")
            if parts[0] == "flowerpose" and len(parts) > 1 and parts[1] in PACKAGES:
                found.add(parts[1])
    return found


def _allowed(path: Path, where: set[str] | Path) -> bool:
    """Whether a module is one `where` names, or lies in the folder it is."""
    return where in path.parents if isinstance(where, Path) else path.name in where


def _modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("folder, forbidden, allowed_in", [
    ("pipeline", {"sim", "hardware", "eval"}, {}),
    ("sim", {"pipeline", "hardware", "eval"}, {}),
    ("hardware", {"sim", "eval"}, {"sim": {"sim_bot.py", "sim_camera.py"}}),
    ("flowerpose", {"pipeline", "sim", "hardware", "eval"}, {
        name: COMMAND_LINE for name in ("pipeline", "sim", "hardware", "eval")}),
])
def test_each_package_imports_only_what_the_layout_allows(folder, forbidden, allowed_in):
    modules = _modules(folder)
    assert modules
    broken = {f"{path.relative_to(ROOT)} imports {package}" for path in modules
              for package in _imports(path) & forbidden
              if not _allowed(path, allowed_in.get(package, set()))}
    assert not broken, sorted(broken)


def test_importing_every_pipeline_module_loads_no_sim_hardware_or_eval_module():
    """The rule as a user meets it: the pipeline alone, installed on a field machine, never
    pulls in the simulator, the bot or the harness (an import the source reading could miss,
    e.g. one made by a library on the pipeline's behalf, shows here)."""
    import subprocess
    import sys

    modules = [f"flowerpose.pipeline.{p.stem}" for p in _modules("pipeline")
               if p.stem != "__init__"]
    script = ("import sys\n" + "".join(f"import {m}\n" for m in modules) +
              "print('\\n'.join(sorted(m for m in sys.modules if m.split('.')[:2] in "
              "(['flowerpose', 'sim'], ['flowerpose', 'hardware'], ['flowerpose', 'eval']))))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, check=True)
    assert done.stdout.split() == [], done.stdout


def _package_imports(folder: Path, package: str) -> dict[str, set[str]]:
    """Each module of one package folder -> the modules of the same folder it imports,
    anywhere (under `if TYPE_CHECKING:` too: a type is a dependency)."""
    modules = {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}
    graph = {}
    for name in modules:
        found = set()
        for node in ast.walk(ast.parse((folder / f"{name}.py").read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                if node.module == package:
                    found |= {a.name for a in node.names}
                elif node.module.startswith(package + "."):
                    found.add(node.module[len(package) + 1:].split(".")[0])
            elif isinstance(node, ast.Import):
                found |= {a.name[len(package) + 1:].split(".")[0] for a in node.names
                          if a.name.startswith(package + ".")}
        graph[name] = (found & modules) - {name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of the graph, as the modules along it, or None."""
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        path.append(module)
        for other in sorted(graph[module]):
            if state.get(other) == 1:
                return path[path.index(other):] + [other]
            if other not in state and (found := visit(other)):
                return found
        state[module] = 2
        path.pop()
        return None

    for module in sorted(graph):
        if module not in state and (found := visit(module)):
            return found
    return None


@pytest.mark.parametrize("folder, package", [
    ("pipeline", "flowerpose.pipeline"), ("eval", "flowerpose.eval"), ("sim", "flowerpose.sim"),
    ("hardware", "flowerpose.hardware"), ("hardware/backends", "flowerpose.hardware.backends"),
    ("hardware/flights", "flowerpose.hardware.flights"), ("flowerpose", "flowerpose")])
def test_no_import_circle_within_a_package(folder, package):
    assert _cycle(_package_imports(ROOT / folder, package)) is None


#: Most lines a module may have: past it, a module holds more than one job.
MAX_MODULE_LINES = 700


def test_every_module_is_at_most_max_module_lines():
    long = sorted(f"{path.relative_to(ROOT)}: {lines} lines"
                  for folder in ("pipeline", "sim", "hardware", "eval", "flowerpose")
                  for path in _modules(folder)
                  if (lines := len(path.read_text().splitlines())) > MAX_MODULE_LINES)
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_an_import_circle_is_found():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None
