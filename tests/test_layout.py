"""The house's shape (issue 31), kept: one import root, the runtime apart from the tools, config errors
raised from the section a module was given, and functions and signatures of a readable size."""
import ast
import pathlib
import re

import pytest

from tests.conftest import ROOT

PRODUCTION = ("tecdard", "drivers", "control", "robots", "sim", "ros2")
BELOW_TECDARD = ("drivers", "control", "robots", "sim", "ros2")      # installed as tecdard.drivers, ...
MAX_FUNCTION_LINES = 100
MAX_PARAMETERS = 12
MAX_FILE_LINES = 550           # "not much over 500"
BARE_IMPORT = re.compile(r"^\s*(from|import)\s+(control|drivers|robots|sim|ros2)(\.|\s|$)", re.M)


def sources(*folders: str):
    for folder in folders:
        yield from sorted((ROOT / folder).rglob("*.py"))


def imported_modules(path: pathlib.Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_every_import_is_under_the_one_root():
    """Bare `control`, `drivers`, `robots` or `sim` would import the checkout's folders as top-level
    packages (a second copy of each module) and fail on a wheel. Strings count too: a test's plugin
    source, a benchmark's child script."""
    found = [f"{p.relative_to(ROOT)}:{m.start()}" for folder in PRODUCTION + ("tests", "benchmarks")
             for p in sources(folder) for m in BARE_IMPORT.finditer(p.read_text())]
    assert not found, found


def test_the_runtime_never_imports_a_tool_or_the_command_line():
    found = [(str(p.relative_to(ROOT)), m) for p in sources("tecdard/runtime") for m in imported_modules(p)
             if m.startswith(("tecdard.tools", "tecdard.cli"))]
    assert not found, found


def test_modules_below_tecdard_raise_their_sections_errors():
    """Klipper's way: `raise section.error(key, message)`, never an import of the config module, and
    nobody outside it reaches into a section's private state."""
    imports = [str(p.relative_to(ROOT)) for p in sources(*BELOW_TECDARD) if "tecdard.config" in imported_modules(p)]
    assert not imports, imports
    private = "._" + "raw("          # spelled apart, so that this file does not find itself
    raw = [str(p.relative_to(ROOT)) for p in sources(*PRODUCTION, "tests", "benchmarks")
           if p.name != "config.py" and private in p.read_text()]
    assert not raw, raw


def _functions(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
            if a.args and a.args[0].arg in ("self", "cls"):
                n -= 1
            yield node, node.end_lineno - node.lineno + 1, n


@pytest.mark.parametrize("folder", PRODUCTION)
def test_functions_files_and_signatures_stay_readable(folder):
    """Records, not long lists of scalars (the compiled kernels included); functions split where they
    grow; files that say one thing."""
    long, wide, big = [], [], []
    for path in sources(folder):
        where = path.relative_to(ROOT)
        lines = len(path.read_text().splitlines())
        if lines > MAX_FILE_LINES:
            big.append(f"{where}: {lines} lines")
        for node, length, params in _functions(path):
            if length > MAX_FUNCTION_LINES:
                long.append(f"{where}:{node.lineno} {node.name}: {length} lines")
            if params > MAX_PARAMETERS:
                wide.append(f"{where}:{node.lineno} {node.name}: {params} parameters")
    assert not (long or wide or big), long + wide + big


def test_the_client_imports_without_the_estimator_pinocchio_or_numba():
    """A planner's process takes `tecdard.client` alone (issue 33): none of the daemon's heavy parts."""
    import subprocess
    import sys
    code = ("import sys\n"
            "for m in ('pinocchio', 'numba', 'ruckig', 'mujoco', 'tecdard.control', 'tecdard.runtime', "
            "'tecdard.robots'):\n"
            "    sys.modules[m] = None\n"
            "from tecdard.client import Client, ClientError\n"
            "print(Client.__name__)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stdout.strip() == "Client", res.stderr


def test_every_markdown_table_has_as_many_cells_as_its_header():
    """benchmarks/daemon.md's table did not render: its separator and its failed rows were short."""
    import pathlib
    import re
    root = pathlib.Path(__file__).resolve().parents[1]
    bad = []
    pages = [root / "README.md", *sorted((root / "docs").glob("*.md")), *sorted((root / "benchmarks").glob("*.md"))]
    for path in pages:
        header = None
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if not line.startswith("|"):
                header = None
                continue
            cells = len(re.split(r"(?<!\\)\|", line.strip().strip("|")))
            if header is None:
                header = cells
            elif cells != header:
                bad.append(f"{path.name}:{n}: {cells} cells, header {header}")
    assert not bad, bad


def test_the_shipped_foxglove_layout_names_only_what_tecdar_writes():
    """Issue 33: a Foxglove layout ships with the project; every topic it reads is one that the export
    and the live view write, and every panel in its tree is configured."""
    import json
    import pathlib
    import re
    root = pathlib.Path(__file__).resolve().parents[1]
    layout = json.loads((root / "docs" / "foxglove" / "tecdar-layout.json").read_text())
    src = (root / "tecdard" / "recording" / "foxglove.py").read_text()
    topics = set(re.findall(r'"(/[a-z_/]+)"', src.split("TOPICS = ")[1].split(")")[0]))
    assert {"/imu", "/tf", "/contact", "/events", "/imu/mean", "/joint_states", "/robot_description"} <= topics
    text = json.dumps(layout["configById"])
    used = set(re.findall(r'"(/[a-z_/]+)(?:\.[a-z.]+)?"', text))
    assert used and used <= topics, used - topics

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])
    assert set(leaves(layout["layout"])) == set(layout["configById"])
