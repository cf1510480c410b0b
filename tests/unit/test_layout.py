"""The house's arrows point one way, as the design card names them: ``service -> worker -> symgs_core``, and
``service, worker -> api_schemas``; the service takes what it needs of the worker package through
``worker.gateway`` alone, and the core imports none of the others."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _imports(package: str) -> dict[str, set[str]]:
    """The absolute modules each file of ``package`` imports (relative imports stay inside it)."""
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
        found[str(path.relative_to(ROOT))] = names
    return found


def _reaching(package: str, into: str) -> dict[str, set[str]]:
    return {file: {n for n in names if n == into or n.startswith(into + ".")}
            for file, names in _imports(package).items()
            if any(n == into or n.startswith(into + ".") for n in names)}  # fmt: skip


def test_the_core_and_the_contract_import_none_of_the_service_layers() -> None:
    layers = {"symgs_core": ("api_schemas", "service", "worker"), "api_schemas": ("service", "worker")}
    for package, others in layers.items():
        for other in others:
            assert _reaching(package, other) == {}, f"{package} imports {other}"


def test_the_worker_imports_nothing_of_the_service() -> None:
    assert _reaching("worker", "service") == {}


def test_the_service_takes_the_worker_package_through_its_gateway_alone() -> None:
    reaching = _reaching("service", "worker")
    assert reaching and all(names == {"worker.gateway"} for names in reaching.values()), reaching
