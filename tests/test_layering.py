"""The layout's import rules (DESIGN.md, "Layout"), read from the source: every import,
at module level or inside a function."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"pipeline", "sim", "hardware", "eval"}
#: The command line's modules: the one place in flowerpose/ that may use every package.
COMMAND_LINE = {"cli.py", "cli_eval.py", "cli_field.py", "cli_options.py", "cli_stages.py",
                "cli_study.py"}


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
    broken = {f"{path.name} imports {package}" for path in modules
              for package in _imports(path) & forbidden
              if path.name not in allowed_in.get(package, set())}
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
