"""The shape of the code, held by its imports (docs/architecture.md): a wing per job, imports
pointing one way, no cycles. Read with the stdlib's `ast`, every import counted, lazy ones
inside functions and `if TYPE_CHECKING:` ones too: a lazy import is still a dependency."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCE_ROOTS = {"leveler": REPO / "leveler", "leveler.drivers": REPO / "drivers/leveler/drivers",
                "leveler.sim": REPO / "sim/leveler/sim"}

#: modules at the root of `leveler`: the shared vocabulary and what composes the wings
ROOT = {"errors": "kit", "records": "kit", "typed_config": "kit", "rt": "kit", "jit": "kit",
        "__init__": "kit", "settings": "settings", "stand": "stand", "virtual": "virtual"}
WINGS = {"loop", "daemon", "log", "analysis", "procedures", "emulate", "live", "cli", "drivers",
         "sim"}

#: what each wing may import besides itself
ALLOWED: dict[str, set[str]] = {
    "kit": set(),
    "sim": {"kit"},
    "drivers": {"kit", "sim"},
    "loop": {"kit", "drivers"},
    "log": {"kit"},
    "settings": {"kit", "drivers", "sim", "loop", "log", "live"},  # each wing's config
    "stand": {"kit", "settings", "drivers", "sim"},
    "virtual": {"kit", "settings", "stand", "drivers", "sim", "loop", "log"},
    "emulate": {"kit", "drivers", "sim"},
    "analysis": {"kit", "settings", "stand", "virtual", "drivers", "sim", "loop", "log"},
    "procedures": {"kit", "settings", "stand", "virtual", "drivers", "sim", "loop", "log",
                   "analysis"},
    "live": {"kit", "log", "analysis"},
    "daemon": {"kit", "settings", "stand", "drivers", "sim", "loop", "log", "analysis", "live"},
    "cli": {"kit", "settings", "stand", "virtual", "drivers", "sim", "loop", "log", "analysis",
            "procedures", "daemon", "emulate", "live"},
}


def modules() -> dict[str, Path]:
    """Every module's dotted name and file, across the three source roots."""
    found: dict[str, Path] = {}
    for pkg, root in SOURCE_ROOTS.items():
        for path in root.rglob("*.py"):
            rel = path.relative_to(root).with_suffix("").parts
            found[".".join((pkg, *rel)).removesuffix(".__init__")] = path
    return found


def wing(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "kit"
    if parts[1] in WINGS:
        return parts[1]
    assert len(parts) == 2 and parts[1] in ROOT, f"{module}: neither a wing nor a root module"
    return ROOT[parts[1]]


def imports(module: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """The leveler modules `module` imports: `from a.b import c` is a.b.c if that is a module."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.split(".")[0] == "leveler")
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] != "leveler":
                continue
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                yield sub if sub in known else node.module


def graph() -> dict[str, set[str]]:
    known = modules()
    return {m: {t for t in imports(m, p, known) if t != m} for m, p in known.items()}


def test_every_root_module_is_vocabulary_or_composition_not_a_wings_job() -> None:
    root = {p.stem for p in SOURCE_ROOTS["leveler"].glob("*.py")}
    assert root == set(ROOT), f"new at the root of leveler/: {sorted(root - set(ROOT))}"


def test_imports_point_one_way() -> None:
    wrong = [f"{m} ({wing(m)}) imports {t} ({wing(t)})"
             for m, targets in graph().items() for t in sorted(targets)
             if wing(t) != wing(m) and wing(t) not in ALLOWED[wing(m)]]
    assert not wrong, "\n".join(wrong)


def test_no_module_imports_another_that_imports_it_back() -> None:
    g = graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while (w := stack.pop()) != v:
                comp.append(w)
            if comp:
                cycles.append(sorted([v, *comp]))

    for v in sorted(g):
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_the_rules_see_what_they_judge() -> None:
    """The walk finds the modules and the imports it rules on: a walk that found nothing
    would pass every rule."""
    g = graph()
    assert len(g) > 60
    assert "leveler.loop.pid" in g["leveler.loop.cycle"]
    assert "leveler.sim.plant" in g["leveler.stand"]
    assert wing("leveler.daemon.service") == "daemon" and wing("leveler.settings") == "settings"


def test_the_wheel_ships_every_package() -> None:
    """pyproject lists the packages by hand (three source roots): a wing missing from the
    list works in a checkout and is absent from a wheel, so the list is held to the tree."""
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
                 ["packages"])
    on_disk = {m for m, p in modules().items() if p.name == "__init__.py"}
    assert listed == on_disk, (sorted(on_disk - listed), sorted(listed - on_disk))
