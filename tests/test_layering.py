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


#: The floors of eval/'s subpackages (DESIGN.md, "Layout"): a module imports from its own
#: subpackage and from those on lower floors only, never sideways or up.
EVAL_FLOORS = {"pool": 0, "scoring": 1, "capture": 1, "reports": 2, "pollination": 2,
               "jobs": 3, "field": 4, "labelling": 4, "studies": 5}
#: The field runs of a bed that has no truth: they import nothing of the scoring.
WITHOUT_TRUTH = ("field/bed_loop.py", "field/physical_bed.py")


def _eval_parts(path: Path) -> set[str]:
    """The eval/ subpackages (or pool) a module imports, anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        if isinstance(node, ast.ImportFrom) and node.module == "flowerpose.eval":
            names = [f"flowerpose.eval.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[:2] == ["flowerpose", "eval"] and len(parts) > 2:
                found.add(parts[2])
    return found


def _eval_part(path: Path, root: Path = ROOT) -> str:
    relative = path.relative_to(root / "eval")
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def _floor_breaches(root: Path) -> list[str]:
    """Every import in root/eval/ of a subpackage beside or above the module's own."""
    broken = []
    for path in sorted((root / "eval").rglob("*.py")):
        if path.parent == root / "eval" and path.name == "__init__.py":
            continue
        own = _eval_part(path, root)
        for part in sorted(_eval_parts(path) - {own}):
            if part not in EVAL_FLOORS or EVAL_FLOORS[part] >= EVAL_FLOORS[own]:
                broken.append(f"{path.relative_to(root)} ({own}, floor "
                              f"{EVAL_FLOORS.get(own)}) imports {part}")
    return broken


def test_every_eval_module_lies_on_a_floor():
    placed = {_eval_part(p) for p in _modules("eval") if p.name != "__init__.py"
              or p.parent != ROOT / "eval"}
    assert placed == set(EVAL_FLOORS), placed ^ set(EVAL_FLOORS)


def test_eval_imports_only_from_its_own_floor_or_below():
    broken = _floor_breaches(ROOT)
    assert not broken, broken


def test_field_runs_without_truth_import_no_scoring():
    for name in WITHOUT_TRUTH:
        assert "scoring" not in _eval_parts(ROOT / "eval" / name), name


def test_a_floor_breach_is_found(tmp_path):
    """The floor test reads what it should: a study importing scoring passes, scoring
    importing a study (inside a function) or a sibling floor does not."""
    for name, text in (("studies/a.py", "from flowerpose.eval.scoring import match\n"),
                       ("scoring/b.py", "def f():\n    from flowerpose.eval.studies import a\n"),
                       ("capture/c.py", "from flowerpose.eval.scoring.match import x\n")):
        (tmp_path / "eval" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "eval" / name).write_text(text)
    assert _floor_breaches(tmp_path) == [
        "eval/capture/c.py (capture, floor 1) imports scoring",
        "eval/scoring/b.py (scoring, floor 1) imports studies"]


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
    ("pipeline", "flowerpose.pipeline"), ("eval", "flowerpose.eval"),
    *((f"eval/{part}", f"flowerpose.eval.{part}") for part in EVAL_FLOORS if part != "pool"),
    ("flowerpose/cli", "flowerpose.cli"), ("sim", "flowerpose.sim"),
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
