"""The import graph: no arrow up the layers (core <- msg_adapters <- gausem_ros; the benchmark harness above all),
no module imports another's private names, and no core modules import each other round a loop; the ROS nodes read
the core only through its public API, and the tracking node stays thin."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# package -> the first-party packages it must never import
FORBIDDEN = {"gausem_core": {"msg_adapters", "gausem_ros", "gausem_bench", "benchmarks"},
             "msg_adapters": {"gausem_ros", "gausem_bench", "benchmarks"},
             "gausem_ros": {"gausem_bench", "benchmarks"}}


def imports(path: Path, runtime: bool = False):
    """(absolute module name, imported names) of every import in ``path`` (relative ones resolved); ``runtime``: not
    those under ``if TYPE_CHECKING:``."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    tree = ast.parse(path.read_text(), str(path))
    typing_only = {id(node) for block in ast.walk(tree) if runtime and isinstance(block, ast.If)
                   and "TYPE_CHECKING" in ast.unparse(block.test) for node in ast.walk(block)}
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            yield from ((alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = list(parts[:-1])  # the package the module (or __init__) is in
            if node.level:
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            yield module, [alias.name for alias in node.names]


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_no_arrow_up_the_layers_and_no_private_imports(package):
    offences = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for module, names in imports(path):
            if module.split(".")[0] in FORBIDDEN[package]:
                offences.append(f"{path.relative_to(ROOT)} imports {module}")
            first_party = module.split(".")[0] in {"gausem_core", "msg_adapters", "gausem_ros"}
            offences += [f"{path.relative_to(ROOT)} imports the private {module}.{name}"
                         for name in names if first_party and name.startswith("_") and not name.startswith("__")]
    assert not offences, "\n".join(offences)


def test_the_check_sees_relative_imports():
    found = dict(imports(ROOT / "gausem_ros" / "launcher.py"))
    assert found["gausem_ros.nodes"] == ["NODE_MODULES"] and "gausem_ros.preflight" in found


def test_no_import_cycle_in_the_core():
    """Imports at run time, at module level or in a function (``if TYPE_CHECKING:`` ones do not count)."""
    modules = {".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): path
               for path in (ROOT / "gausem_core").rglob("*.py")}
    graph = {name: sorted({target for module, names in imports(path, runtime=True)
                           for target in (module, *(f"{module}.{n}" for n in names)) if target in modules} - {name})
             for name, path in modules.items()}
    cycles, done = [], set()

    def visit(name: str, path: list[str]) -> None:
        for target in graph[name]:
            if target in path:
                cycles.append(" -> ".join(path[path.index(target):] + [target]))
            elif target not in done:
                visit(target, path + [target])
        done.add(name)
    for name in sorted(graph):
        if name not in done:
            visit(name, [name])
    assert graph["gausem_core.slam.system"], "the check sees no imports"
    assert not cycles, "\n".join(cycles)


def test_the_ros_nodes_read_the_core_only_through_its_public_api():
    """No ``back_end.`` in gausem_ros: events (``slam.events``) and ``GauSemSLAM``'s methods and properties only."""
    offences = [f"{path.relative_to(ROOT)}:{number}" for path in sorted((ROOT / "gausem_ros").rglob("*.py"))
                for number, line in enumerate(path.read_text().splitlines(), 1) if "back_end." in line]
    assert not offences, "\n".join(offences)


def test_the_tracking_node_is_thin_and_its_parts_small():
    """tracking_mapping.py (inputs, the call into the core, the wiring) under 300 lines; each of its parts
    (gausem_ros/nodes/tracking/) at most 250."""
    nodes = ROOT / "gausem_ros" / "nodes"
    parts = sorted((nodes / "tracking").glob("*.py"))
    assert len((nodes / "tracking_mapping.py").read_text().splitlines()) < 300
    assert len(parts) > 5 and {p.name: n for p in parts if (n := len(p.read_text().splitlines())) > 250} == {}
