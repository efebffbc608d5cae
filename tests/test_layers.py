"""The dependency rule of docs/design.md: schemas <- stages <- pipeline <- flows."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
ALLOWED = {
    "schemas": {"schemas"},
    "stages": {"schemas", "stages"},
    "pipeline": {"schemas", "stages", "pipeline"},
    "flows": {"schemas", "stages", "pipeline", "flows"},
}


def imported_layers(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names & set(ALLOWED)


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layer_imports_only_what_it_may(layer):
    bad = {}
    for path in (ROOT / layer).rglob("*.py"):
        extra = imported_layers(path) - ALLOWED[layer]
        if extra:
            bad[str(path.relative_to(ROOT))] = sorted(extra)
    assert not bad, f"{layer} may import only {sorted(ALLOWED[layer])}: {bad}"


def test_schemas_import_pyarrow_only():
    third_party = set()
    for path in (ROOT / "schemas").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                third_party.add(node.module.split(".")[0])
            elif isinstance(node, ast.Import):
                third_party |= {a.name.split(".")[0] for a in node.names}
    assert third_party <= {"pyarrow", "schemas", "__future__", "dataclasses", "importlib"}, \
        third_party


#: The rooms of pipeline/ (see pipeline/__init__.py) and the rooms each may import.
ROOMS = {
    "io": {"io"},
    "offline": {"io", "offline"},
    "stream": {"io", "offline", "stream"},
    "report": {"io", "offline", "report"},
    "view": {"io", "offline", "stream", "view"},
    "cli": {"io", "offline", "stream", "report", "view", "cli"},
}


def imported_rooms(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    rooms = set()
    for node in ast.walk(tree):
        mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
            [node.module] if isinstance(node, ast.ImportFrom) and node.module \
            and node.level == 0 else []
        for m in mods:
            parts = m.split(".")
            if parts[0] == "pipeline" and len(parts) > 1:
                rooms.add(parts[1])
            if isinstance(node, ast.ImportFrom) and m == "pipeline":
                rooms |= {a.name for a in node.names}
    return rooms


@pytest.mark.parametrize("room", sorted(ROOMS))
def test_pipeline_rooms_import_only_what_they_may(room):
    bad = {}
    for path in (ROOT / "pipeline" / room).rglob("*.py"):
        extra = imported_rooms(path) - ROOMS[room]
        if extra:
            bad[str(path.relative_to(ROOT))] = sorted(extra)
    assert not bad, f"pipeline/{room} may import only {sorted(ROOMS[room])}: {bad}"


def test_every_pipeline_module_lives_in_a_room():
    loose = [p.name for p in (ROOT / "pipeline").glob("*.py") if p.name != "__init__.py"]
    assert not loose, f"modules outside the rooms of pipeline/: {loose}"


def test_no_import_circle_between_modules_of_pipeline():
    """No module of pipeline imports, even lazily, a module that imports it back."""
    graph: dict[str, set[str]] = {}
    for path in (ROOT / "pipeline").rglob("*.py"):
        mod = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        tree = ast.parse(path.read_text())
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 \
                    and node.module.startswith("pipeline."):
                deps.add(node.module)
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("pipeline.")}
        graph[mod] = deps
    pairs = sorted((a, b) for a, ds in graph.items() for b in ds
                   if a < b and a in graph.get(b, set()))
    assert not pairs, f"modules that import each other: {pairs}"
