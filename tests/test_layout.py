"""The package's structure: no import circles; imports run down the layers and no two units
import each other (imports inside functions and lazy "module:attr" strings included); no other
package's private parts; citations that exist; modules of one idea."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import dlocli

ROOT = Path(dlocli.__file__).parent


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking_block(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


#: modules whose ``"module:attr"`` strings name what sits above them, by design: the registry
#: (each kind's ``home``, imported to register its built-ins) and the package's namespace
#: (its public names, each imported on first use; Python imports it before any submodule)
NAMES_WHAT_IS_ABOVE = {"dlocli", "dlocli.registry"}


def _absolute(node: ast.ImportFrom, package: str) -> str:
    """The module an ``from ... import`` names, a relative one resolved from ``package``."""
    if not node.level:
        return node.module or ""
    base = package.split(".")[: len(package.split(".")) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def imported(path: Path, modules: set[str], root: Path = ROOT) -> set[str]:
    """The modules of the package ``path`` imports anywhere (not under ``if TYPE_CHECKING``):
    ``import``, ``from ... import`` (relative ones too), and a ``"module:attr"`` or
    ``"module"`` string naming a module of another unit (a lazy import: a registry's target,
    ``importlib.import_module``'s argument), except in :data:`NAMES_WHAT_IS_ABOVE`."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    skip = {
        id(n) for block in ast.walk(tree) if _type_checking_block(block) for n in ast.walk(block)
    }
    target = re.compile(rf"({re.escape(root.name)}(?:\.\w+)+)(?::\w+)?")
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            module = _absolute(node, package)
            names = [module] + [f"{module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            lazy = target.fullmatch(node.value)
            outside = lazy and unit(lazy.group(1)) != unit(name)  # its own unit's: not a loop
            names = [lazy.group(1)] if outside and name not in NAMES_WHAT_IS_ABOVE else []
        found |= {name for name in names if name in modules}
    return found


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    paths = {module_name(p, root): p for p in root.rglob("*.py")}
    modules = set(paths)
    return {name: imported(path, modules, root) - {name} for name, path in paths.items()}


def cycle_from(graph: dict[str, set[str]], start: str) -> list[str] | None:
    stack, seen = [(start, [start])], set()
    while stack:
        node, path = stack.pop()
        for nxt in graph.get(node, ()):
            if nxt == start:
                return [*path, start]
            if nxt not in seen:
                seen.add(nxt)
                stack.append((nxt, [*path, nxt]))
    return None


def test_no_import_circles():
    graph = import_graph()
    cycles = [c for c in (cycle_from(graph, m) for m in sorted(graph)) if c]
    assert not cycles, " | ".join(" -> ".join(c) for c in cycles[:5])


def test_the_walker_sees_circles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycle_from(graph, "a") == ["a", "b", "c", "a"] and cycle_from(graph, "d") is None


# ------------------------------------------------------------------ layers
#: dlocli's top-level modules and folders from the lowest to the highest (ARCHITECTURE.md's
#: rooms): each imports only what comes before it, imports inside functions included;
#: lazy "module:attr" strings included; `dlocli` is the package's own __init__. What a lower
#: layer needs of a higher one comes through a registry: the cell's client
#: (dlocli.registry.cells), the point-cloud observer (dlocli.registry.observers)
LAYERS = [
    # foundations: errors, cancellation, events, files, limits, registries, specs
    "errors", "cancel", "events", "threads", "migrations", "tensorboard", "io", "limits",
    "extras", "registry", "spec_base", "rundir", "processes", "camera_spec", "backend_spec",
    "specs", "cell_spec", "resume", "executors",
    # data, simulators, the task (and the package's namespace over it), learned models,
    # recordings, the depth camera and tracker
    "data", "backends", "env", "dlocli", "models", "recorded_cables", "tracking",
    # what acts on the rod, its figures, the calibration, the served cell
    "controllers", "plots", "calibration", "bridge",
    # the commands' runs, the bench over them, the CLI
    "runs", "bench", "cli", "__main__",
]  # fmt: skip


def unit(module: str) -> str:
    """The top-level module or folder of dlocli a module belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def upward_imports(graph: dict[str, set[str]], layers: list[str]) -> list[str]:
    """``a -> b`` for each import of a module of a lower unit's from a higher one's, or of a
    unit ``layers`` does not place."""
    rank = {name: i for i, name in enumerate(layers)}
    found = []
    for module, imports in sorted(graph.items()):
        for target in sorted(imports):
            low, high = unit(module), unit(target)
            if low == high:
                continue
            if low not in rank or high not in rank or rank[high] > rank[low]:
                found.append(f"{module} -> {target}")
    return found


def mutual_units(graph: dict[str, set[str]]) -> list[str]:
    """``a <-> b`` for each two units that import each other (by any of their modules)."""
    edges = {(unit(m), unit(t)) for m, imports in graph.items() for t in imports}
    return sorted(f"{a} <-> {b}" for a, b in edges if a < b and (b, a) in edges)


def test_imports_run_down_the_layers():
    graph = import_graph()
    assert {unit(m) for m in graph} == set(LAYERS), "place each new module or folder in LAYERS"
    assert not upward_imports(graph, LAYERS), upward_imports(graph, LAYERS)


def test_no_two_folders_import_each_other():
    assert not mutual_units(import_graph()), mutual_units(import_graph())


def test_the_layer_check_sees_an_upward_import_and_a_pair():
    layers = ["errors", "models", "plots"]
    fine = {"dlocli.errors": set(), "dlocli.models.a": {"dlocli.errors"},
            "dlocli.models.b": {"dlocli.models.a"},
            "dlocli.plots": {"dlocli.models.b"}}  # fmt: skip
    assert upward_imports(fine, layers) == [] and mutual_units(fine) == []
    looped = {**fine, "dlocli.models.c": {"dlocli.plots"}}
    assert upward_imports(looped, layers) == ["dlocli.models.c -> dlocli.plots"]
    assert mutual_units(looped) == ["models <-> plots"]
    unplaced = {**fine, "dlocli.tracking.x": {"dlocli.errors"}}
    assert upward_imports(unplaced, layers) == ["dlocli.tracking.x -> dlocli.errors"]


def test_the_layer_check_reads_every_kind_of_import(tmp_path):
    """On a small package written out: an import inside a function, a relative one and a lazy
    ``"module:attr"`` string each count; one under ``if TYPE_CHECKING`` does not."""
    files = {
        "__init__.py": "",
        "errors.py": "",
        "low/__init__.py": "",
        "low/a.py": "import pkg.errors\n\ndef late():\n    from pkg.high import b\n",
        "low/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.high.b\n",
        "low/d.py": 'TARGET = "pkg.high.b:thing"\nOWN = "pkg.low.a:late"\n',
        "high/__init__.py": "",
        "high/b.py": "from ..low import a\n",
    }
    for name, text in files.items():
        (tmp_path / "pkg" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "pkg" / name).write_text(text)
    layers = ["errors", "low", "high"]
    graph = import_graph(tmp_path / "pkg")
    assert graph["pkg.high.b"] == {"pkg.low", "pkg.low.a"} and graph["pkg.low.c"] == set()
    assert upward_imports(graph, layers) == [
        "pkg.low.a -> pkg.high", "pkg.low.a -> pkg.high.b", "pkg.low.d -> pkg.high.b"
    ]  # fmt: skip
    assert mutual_units(graph) == ["high <-> low"]
    (tmp_path / "pkg/low/a.py").write_text("import pkg.errors\n")
    (tmp_path / "pkg/low/d.py").write_text('OWN = "pkg.low.a:late"\n')
    graph = import_graph(tmp_path / "pkg")
    assert upward_imports(graph, layers) == [] and mutual_units(graph) == []


# ------------------------------------------------------------------ other packages' insides
#: documented public names that start with an underscore
PUBLIC_UNDERSCORED = {"os._exit"}


def _private(dotted: str) -> bool:
    parts = dotted.split(".")
    return dotted not in PUBLIC_UNDERSCORED and any(
        part.startswith("_") and not part.startswith("__") for part in parts
    )


def private_imports(source: str) -> list[str]:
    """What ``source`` takes from another package's private parts: an import of a module or
    name starting with ``_`` (``typer._click``), or such an attribute of an imported package."""
    tree = ast.parse(source)
    packages = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.Import)
                for a in n.names if not a.name.startswith("dlocli")}  # fmt: skip
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if _private(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if not node.module.startswith("dlocli"):
                names = [f"{node.module}.{a.name}" for a in node.names]
                found += [name for name in names if _private(name)]
        elif isinstance(node, ast.Attribute) and ast.unparse(node.value) in packages:
            found += [name] if _private(name := ast.unparse(node)) else []
    return found


def test_no_private_import_of_another_package():
    """dlocli uses Typer (and the Click it carries) and every other dependency through their
    public names only: no ``typer._click``."""
    found = {str(p.relative_to(ROOT.parent)): private_imports(p.read_text())
             for p in sorted(ROOT.rglob("*.py"))}  # fmt: skip
    assert not {path: names for path, names in found.items() if names}


def test_the_private_import_check_sees_one():
    source = "import typer\nimport typer.main\nfrom typer._click import Context\nx = typer._click\n"
    assert private_imports(source) == ["typer._click.Context", "typer._click"]
    fine = "from __future__ import annotations\nimport os\nimport typer.core\nos._exit(0)\n"
    assert private_imports(fine) == []


# ------------------------------------------------------------------ what the source cites
#: a `dlocli.x.y` path, and a repository path (examples/..., benchmarks/..., tests/..., dlocli/...)
DOTTED = re.compile(r"\bdlocli(?:\.[A-Za-z_]\w*)+")
REPO_PATH = re.compile(r"(?<![\w/.])((?:examples|benchmarks|tests|dlocli)/[\w./-]*\w)")
#: names shaped like these that are not citations: Gymnasium / Minari ids, a metadata key,
#: the entry-point group of plugin commands
NOT_CITATIONS = re.compile(r"-v\d+$|^dlocli\.observation_layout$|^dlocli\.commands$")
#: files users do not have
ABSENT = re.compile(r"\b(DESIGN\.md|FINDINGS(?:\.md)?)\b")


def module_file(parts: list[str]) -> Path | None:
    path = ROOT.parent.joinpath(*parts)
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def dotted_path_exists(dotted: str) -> bool:
    """The longest module prefix exists, and the next name is defined in it (if any)."""
    parts = dotted.split(".")
    k = len(parts)
    while k > 1 and module_file(parts[:k]) is None:
        k -= 1
    source = module_file(parts[:k]).read_text()  # dlocli itself always exists
    rest = parts[k:]
    defined = rf"(def|class)\s+{rest[0]}\b|^\s*{rest[0]}\s*[:=]|\"{rest[0]}\"" if rest else ""
    return not rest or re.search(defined, source, re.M) is not None


def broken_citations(path: Path) -> list[str]:
    found = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        where = f"{path.relative_to(ROOT.parent)}:{number}"
        dotted = [m.group(0) for m in DOTTED.finditer(line) if not NOT_CITATIONS.search(m.group(0))]
        found += [f"{where} {name}" for name in dotted if not dotted_path_exists(name)]
        found += [f"{where} {m.group(1)}" for m in REPO_PATH.finditer(line)
                  if "*" not in m.group(1) and not NOT_CITATIONS.search(m.group(1))
                  and not ROOT.parent.joinpath(m.group(1)).exists()
                  and not ROOT.parent.joinpath(m.group(1) + ".py").exists()]  # fmt: skip
        found += [f"{where} {m.group(1)}" for m in ABSENT.finditer(line)]
    return found


def test_the_package_cites_only_what_exists():
    """Docstrings and comments name modules, attributes and files that exist, and no file
    users lack (DESIGN.md, FINDINGS)."""
    broken = [c for path in sorted(ROOT.rglob("*.py")) for c in broken_citations(path)]
    assert not broken, broken


def test_the_citation_check_sees_a_moved_path(tmp_path):
    assert dotted_path_exists("dlocli.env.metrics.score")
    assert not dotted_path_exists("dlocli.metrics.score")
    assert not dotted_path_exists("dlocli.env.metrics.no_such_function")


# ------------------------------------------------------------------ module size
#: most lines of one module: beyond it a module holds more than one idea
MAX_MODULE_LINES = 500
#: modules over the limit whose split waits for work in progress on them
OVER_THE_LIMIT = {}


def test_no_module_over_500_lines():
    long = {
        str(path.relative_to(ROOT.parent)): n
        for path in sorted(ROOT.rglob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    over = {name: n for name, n in long.items() if name not in OVER_THE_LIMIT}
    assert not over, f"modules over {MAX_MODULE_LINES} lines (split them by idea): {over}"


def test_data_and_models_do_not_import_the_recordings_room():
    """Datasets and models sit below `dlocli/recorded_cables/` (importing recordings): what both
    need of recorded cables (the marker dataset, the DEFORM protocol) lives in `dlocli/data/`."""
    graph = import_graph()
    low = [m for m in graph if m.startswith(("dlocli.data", "dlocli.models"))]
    assert len(low) > 20, "the check would be vacuous: no data or models modules found"
    upward = {m: sorted(i for i in graph[m] if i.startswith("dlocli.recorded_cables")) for m in low}
    assert not {m: i for m, i in upward.items() if i}, upward
