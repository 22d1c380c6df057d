"""The import graph: no arrow up the layers (core <- msg_adapters <- gausem_ros; the benchmark harness above all),
and no module imports another's private names."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# package -> the first-party packages it must never import
FORBIDDEN = {"gausem_core": {"msg_adapters", "gausem_ros", "gausem_bench", "benchmarks"},
             "msg_adapters": {"gausem_ros", "gausem_bench", "benchmarks"},
             "gausem_ros": {"gausem_bench", "benchmarks"}}


def imports(path: Path):
    """(absolute module name, imported names) of every import in ``path`` (relative ones resolved)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
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
