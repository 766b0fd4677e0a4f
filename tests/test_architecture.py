"""Architecture: the import layering of pyproject.toml's import-linter contracts, and no import cycle.

kernels/ and pipelines/ are installed as ti_cmax.kernels and ti_cmax.pipelines (package-dir mapping), which the
import graph's scan of the ti_cmax folder does not see: the checks run in a subprocess on the package assembled
from symbolic links (ti_cmax/, with kernels/ and pipelines/ linked inside), so that they read this checkout's
source files, imports inside functions included.
"""
import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def assembled(tmp_path_factory) -> Path:
    """A folder holding ti_cmax/ as it is installed (links to this checkout's files)."""
    tree = tmp_path_factory.mktemp("assembled")
    pkg = tree / "ti_cmax"
    pkg.mkdir()
    for entry in (ROOT / "ti_cmax").iterdir():
        if entry.name != "__pycache__":
            (pkg / entry.name).symlink_to(entry)
    (pkg / "kernels").symlink_to(ROOT / "kernels")
    (pkg / "pipelines").symlink_to(ROOT / "pipelines")
    return tree


def _run(tree: Path, args: list[str]) -> subprocess.CompletedProcess:
    # cwd and PYTHONPATH the assembled tree: it shadows the installed package for the graph's scan
    return subprocess.run(args, cwd=tree, env={"PYTHONPATH": str(tree), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=120)


def test_import_linter_contracts_are_kept(assembled):
    lint = Path(sys.executable).with_name("lint-imports")
    proc = _run(assembled, [str(lint), "--no-cache", str(ROOT / "pyproject.toml")])
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


CYCLES = textwrap.dedent("""
    import grimp

    graph = grimp.build_graph("ti_cmax", include_external_packages=False, cache_dir=None)
    print(len(graph.modules))
    for importer in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(importer)):
            back = graph.find_shortest_chain(importer=imported, imported=importer)
            if back:
                print("cycle:", " -> ".join((importer,) + tuple(back)))
""")


def test_no_import_cycle_among_the_project_modules(assembled):
    """Counting imports inside functions: a module reachable from what it imports is a cycle."""
    proc = _run(assembled, [sys.executable, "-c", CYCLES])
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert int(lines[0]) > 80  # the scan saw the kernels and pipelines, not only ti_cmax/
    assert lines[1:] == []


MAX_FUNCTION_LINES = 80
# where the limit holds; the Taichi kernels (one launch per step) are exempt
SHORT_FUNCTIONS = ("ti_cmax", "pipelines")


def test_functions_read_in_one_screen():
    """No function (nested ones counted inside their parent) over MAX_FUNCTION_LINES lines: a long one is split
    into named steps."""
    long = []
    for folder in SHORT_FUNCTIONS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > MAX_FUNCTION_LINES:
                        long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert long == []


def test_the_contracts_name_every_core_module():
    """Each module of the CMax-SLAM core (pipelines/*.py) is in the core layer and each CMax kernel module in the
    kernels' contract, so a new module does not escape the layering unseen."""
    tomllib = pytest.importorskip("tomllib")
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c for c in contracts if c["type"] == "layers")["layers"]
    core = {m.strip() for layer in layers if ":" in layer for m in layer.split(":")}
    kernels = set(next(c for c in contracts
                       if c.get("forbidden_modules") == ["ti_cmax.kernels.baselines"])["source_modules"])
    for folder, named in (("pipelines", core), ("kernels", kernels)):
        modules = {f"ti_cmax.{folder}.{p.stem}" for p in (ROOT / folder).glob("*.py") if p.stem != "__init__"}
        assert modules == named, (folder, sorted(modules ^ named))


def test_the_command_line_is_built_without_the_kernel_engine():
    """Every command's arguments (what ``ti-cmax --version`` and ``--help`` build) come from light modules: the
    benchmark's choices from its suites, not from the benchmark and the kernels it runs."""
    code = ("import sys; from ti_cmax.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('taichi', 'quadrants', 'ti_cmax.kernels.runtime') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr
