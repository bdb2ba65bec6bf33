"""The house's shape (issues 31 and 47), kept: one import root, libraries below the command line and no
import circles (lazy imports included), config errors raised from the section a module was given, and
functions and signatures of a readable size."""
import ast
import pathlib
import re

import pytest

from tests.conftest import ROOT

PRODUCTION = ("tecdard", "drivers", "control", "robots", "sim", "ros2")
BELOW_TECDARD = ("drivers", "control", "robots", "sim", "ros2")      # installed as tecdard.drivers, ...
MAX_FUNCTION_LINES = 100
MAX_PARAMETERS = 12
MAX_FILE_LINES = 500
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


INSTALLED_AS = {"tecdard": "tecdard", **{folder: f"tecdard.{folder}" for folder in BELOW_TECDARD}}
COMMAND_LINE = ("tecdard.cli", "tecdard.tools", "tecdard.__main__")     # argument parsing over the libraries


def module_files() -> dict[str, pathlib.Path]:
    """Every production module by its installed name (tecdard.control.geometry: control/geometry.py)."""
    out = {}
    for folder, package in INSTALLED_AS.items():
        for path in sources(folder):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            out[".".join((package, *parts))] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """module -> the modules of ours it imports, anywhere in it (a function's lazy import counts as much
    as one at the top: it is the same dependency, only later)."""
    files = module_files()

    def ours(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                    base = f"{up}.{base}" if base else up
                for alias in node.names:
                    deps.add(ours(f"{base}.{alias.name}") or ours(base))
            elif isinstance(node, ast.Import):
                deps.update(ours(alias.name) for alias in node.names)
        graph[name] = {d for d in deps if d is not None and d != name}
    return graph


def folder_of(module: str) -> str:
    """tecdard.runtime.daemon -> tecdard.runtime; a module at the root (tecdard.config) is its own."""
    return ".".join(module.split(".")[:2])


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's, iterative)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        x = stack.pop()
                        on.discard(x)
                        comp.append(x)
                        if x == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
            elif w not in index:
                index[w] = low[w] = counter[0]
                counter[0] += 1
                stack.append(w)
                on.add(w)
                work.append((w, iter(sorted(graph.get(w, ())))))
            elif w in on:
                low[v] = min(low[v], index[w])
    return out


def test_no_import_circles_between_modules_or_folders_lazy_imports_included():
    """A circle hidden behind a function's import is a circle all the same: a change on either side
    reaches the other, and neither can be read, tested or installed alone."""
    graph = import_graph()
    folders: dict[str, set[str]] = {}
    for module, deps in graph.items():
        folders.setdefault(folder_of(module), set()).update(folder_of(d) for d in deps if folder_of(d) != folder_of(module))
    assert not circles(graph), circles(graph)
    assert not circles(folders), circles(folders)


def test_libraries_never_import_the_command_line():
    """cli/ and tools/ parse arguments and call libraries; nothing below them imports them, so a change
    to `tecdard localize` cannot change what the daemon or the fleet's index computes."""
    found = [f"{m} -> {d}" for m, deps in import_graph().items() if not m.startswith(COMMAND_LINE)
             for d in deps if d.startswith(COMMAND_LINE)]
    assert not found, found


def test_the_fleet_never_imports_the_runtime():
    """fleet/ is data (the store, the index, the roster, the ACL): the daemon uses it, never the other way."""
    found = [f"{m} -> {d}" for m, deps in import_graph().items() if m.startswith("tecdard.fleet")
             for d in deps if d.startswith(("tecdard.runtime", "tecdard.cli", "tecdard.tools"))]
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


def test_the_recording_members_are_declared_once_and_the_docs_follow_the_table():
    """Issue 47: a member is a row of recording/members.py; the Recording and LiveLog records, the reader's
    own checks and docs/recordings.md's tables all follow it (adding a field: the row, its producer, a test)."""
    import dataclasses

    from tecdard.recording import format as F, live as L, members as M
    assert {f.name for f in dataclasses.fields(F.Recording)} == {m.attr for m in M.CORE if m.key != "format"}
    assert {f.name for f in dataclasses.fields(L.LiveLog)} == {m.attr for m in M.LIVE}
    assert set(F.CHECKS) <= {m.key for m in M.CORE}
    by_key, header = {}, None
    for line in (ROOT / "docs" / "recordings.md").read_text().splitlines():
        header = (header or line) if line.startswith("|") else None
        if header == "| key | shape | required | meaning |" and line.startswith("| `"):
            by_key.setdefault(line.split("`")[1], []).append(line)
    assert set(by_key) == set(M.MEMBERS), set(M.MEMBERS) ^ set(by_key)
    wrong = [f"{key}: {lines} != {M.MEMBERS[key].row()}" for key, lines in by_key.items()
             if any(line != M.MEMBERS[key].row() for line in lines)]
    assert not wrong, wrong


def test_the_writer_takes_only_declared_members(tmp_path):
    import numpy as np

    from tecdard.recording.format import Recording, save_recording
    n = 4
    rec = Recording(np.arange(n) * 1e-3, np.zeros((n, 3)), np.zeros((n, 3)), np.arange(n) * 1e-3, np.zeros((n, 3)),
                    np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), np.array([0.0, 0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="live_typo: no live member"):
        save_recording(tmp_path / "x.npz", rec, extra={"live_typo": np.zeros(3)})


QUEUES = ("push", "put", "put_nowait", "offer")


def _imu_chunk(node: ast.Tuple) -> bool:
    return [getattr(e, "id", None) for e in node.elts][1:] == ["gyro", "accel"]


def test_what_crosses_a_thread_is_a_named_record_not_a_long_tuple():
    """Proprioception crossed as a 7-slot tuple packed in one file and unpacked in another; a hand-off
    now carries a record (control.proprio.ProprioSample, runtime.messages, the recorder's) or a pair.
    An IMU chunk is ImuSource.read's (t, gyro, accel), the one triple every source declares."""
    found = []
    for path in sources("tecdard/runtime", "robots", "drivers", "sim"):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in QUEUES
                    and any(isinstance(a, ast.Tuple) and len(a.elts) > 2 and not _imu_chunk(a) for a in node.args)):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, found


def test_tests_are_tests_and_fakes_live_apart():
    """Issue 47: the peers the tests run against (a UR controller, franky-sim, ROS 2 arms and clients, a
    router, a flooder, a CA) live in tests/fakes/, and the tier is a marker beside each slow test, not a list
    kept elsewhere."""
    stray = [p.name for p in (ROOT / "tests").glob("*.py") if not p.name.startswith("test_") and p.name != "conftest.py"]
    assert not stray, stray
    fakes_with_tests = [p.name for p in (ROOT / "tests" / "fakes").glob("*.py")
                        if any(isinstance(n, ast.FunctionDef) and n.name.startswith("test_")
                               for n in ast.parse(p.read_text()).body)]
    assert not fakes_with_tests, fakes_with_tests
    conftest = (ROOT / "tests" / "conftest.py").read_text()
    assert "add_marker" not in conftest and "SLOW_FILES" not in conftest


WALKS_UP = re.compile(r"__file__.*(parents\[|\.parent\.parent|dirname\(\s*os\.path\.dirname)|"
                      r"dirname\(\s*os\.path\.dirname\(.*__file__")


def test_shipped_files_are_found_through_the_installed_package_not_by_walking_up_from_a_source():
    """Issue 47: `Path(__file__).parents[n]` finds the checkout's folders from a source file, and in an
    installed wheel there is no checkout. Shipped data is tecdard.shipped's (the configs, the systemd units,
    the host board), or an option; a module may still name files inside its own package (Path(__file__).parent)."""
    found = [f"{p.relative_to(ROOT)}:{n}" for p in sources(*PRODUCTION)
             for n, line in enumerate(p.read_text().splitlines(), 1) if WALKS_UP.search(line)]
    assert not found, found
    import tecdard.shipped as shipped
    assert shipped.config("sim.yaml").is_file() and shipped.systemd("99-tecdar-imu.rules").is_file()


def test_the_firmware_includes_headers_by_name_on_its_include_paths():
    found = [f"{p.relative_to(ROOT)}:{n}" for p in sorted((ROOT / "firmware").rglob("*.[ch]"))
             for n, line in enumerate(p.read_text().splitlines(), 1) if re.match(r'\s*#include\s+"\.\.?/', line)]
    assert not found, found


def _classes_declaring_options() -> set[str]:
    """Every production class with a field declared through tecdard.options.option."""
    found = set()
    for path in sources(*PRODUCTION):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    isinstance(stmt, ast.AnnAssign) and isinstance(stmt.value, ast.Call)
                    and getattr(stmt.value.func, "id", None) == "option" for stmt in node.body):
                found.add(node.name)
    return found


def test_options_are_declared_once_and_their_docs_and_help_are_made_from_the_declarations():
    """Issue 47: an option is a dataclass field with its key, default, limits, unit and help; the config
    reader (tecdard.options.read_options), docs/options.md and `tecdard options` / `tecdard run --help` come
    from it. Every class that declares options is a section of the list, the page is the list rendered,
    and every key of the shipped configs is declared."""
    import yaml

    from tecdard.cli.options import markdown, sections
    from tecdard.options import declared
    listed = sections()
    assert _classes_declaring_options() == {cls.__name__ for _, cls in listed}
    assert (ROOT / "docs" / "options.md").read_text() == markdown(), "regenerate: tecdard options --markdown"
    keys = {f"{path}.{opt.key or f.name}" for path, cls in listed for f, opt in declared(cls)}

    def leaves(data: dict, prefix: str = ""):
        for key, value in data.items():
            yield from leaves(value, f"{prefix}{key}.") if isinstance(value, dict) else [f"{prefix}{key}"]
    for name in ("sim.yaml", "ur5e.yaml", "fr3.yaml"):
        undeclared = set(leaves(yaml.safe_load((ROOT / "configs" / name).read_text()))) - keys
        assert not undeclared, (name, undeclared)


@pytest.mark.parametrize("folder", BELOW_TECDARD)
def test_the_card_folders_are_linked_under_the_import_root_for_the_tools_that_read_the_house(folder):
    """Issue 47: a type checker or an editor resolves `tecdard.control` by looking in tecdard/; the link makes
    the design card's top-level folder be there too (setuptools' package-dir, which the wheel follows, is no
    file a static tool reads). `make lint` runs mypy through them."""
    link = ROOT / "tecdard" / folder
    assert link.is_symlink() and link.resolve() == (ROOT / folder).resolve(), link
