"""What the package imports is what pyproject.toml declares.

A fresh `pip install .` (the README's first command) installs `dependencies` and nothing else,
so every module dlocli/ imports at module level must come from there, not from an extra or
from another package's requirements; imports inside functions may come from an extra, whose
absence the command that needs it reports in one line.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

from dlocli.extras import EXTRAS

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
#: extras of test and documentation tooling, not features of dlocli
TOOLING_EXTRAS = {"test", "dev", "docs"}


def _distribution(requirement: str) -> str:
    return _normalized(re.split(r"[ <>=!~;\[(]", requirement.strip(), maxsplit=1)[0])


def _normalized(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _module_level_imports(path: Path) -> list[tuple[str, int]]:
    """(top-level module, line) of each import a module runs when it is imported: its body's,
    including inside top-level try/if blocks, but not under ``if TYPE_CHECKING``."""
    found: list[tuple[str, int]] = []

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.Import):
                found.extend((alias.name.split(".")[0], node.lineno) for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.append((node.module.split(".")[0], node.lineno))
            elif isinstance(node, ast.If):
                if "TYPE_CHECKING" not in ast.unparse(node.test):
                    visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                for block in (node.body, node.orelse, node.finalbody):
                    visit(block)
                for handler in node.handlers:
                    visit(handler.body)

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)).body)
    return found


def test_deptry_finds_every_import_declared() -> None:
    """deptry (configured in pyproject.toml) reads every import against the declared
    packages and this environment: a missing one, or one that only arrives through another
    package's requirements, fails here."""
    result = subprocess.run(
        [sys.executable, "-m", "deptry", ".", "--no-ansi"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr


def test_module_level_imports_come_from_dependencies() -> None:
    """deptry counts an extra as declared; the first command installs none of them."""
    required = {_distribution(r) for r in PROJECT["dependencies"]}
    providers = {
        module: {_normalized(d) for d in dists}
        for module, dists in packages_distributions().items()
    }
    wrong = []
    for path in sorted((ROOT / "dlocli").rglob("*.py")):
        for module, line in _module_level_imports(path):
            if module in sys.stdlib_module_names or module == "dlocli" or module == "__future__":
                continue
            if not providers.get(module, set()) & required:
                where = path.relative_to(ROOT)
                wrong.append(f"{where}:{line} imports {module} (from {providers.get(module)})")
    assert not wrong, "module-level imports not in [project] dependencies:\n" + "\n".join(wrong)


def test_the_module_level_check_sees_a_stray_import(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text(
        "import os\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import ray\n"
        "try:\n    import click\nexcept ImportError:\n    pass\n"
        "def f():\n    import minari\n",
        encoding="utf-8",
    )
    assert [m for m, _ in _module_level_imports(source)] == ["os", "typing", "click"]


def test_every_feature_extra_is_known_to_dlocli() -> None:
    """An extra added to pyproject.toml gets its entry in dlocli.extras (and a message)."""
    extras = PROJECT["optional-dependencies"]
    assert set(extras) - TOOLING_EXTRAS == set(EXTRAS)
    providers = packages_distributions()
    for extra, module in EXTRAS.items():
        declared = {_distribution(r) for r in extras[extra]}
        assert {_normalized(d) for d in providers.get(module, [])} & declared, (extra, module)


#: a command that needs each extra (None: nothing needs it, a run just writes less)
NEEDS = {
    "ray": ["online", "--executor", "ray", "--iters", "1"],
    "minari": ["export", "{tmp}/missing-run"],
    "calibrate": ["calibrate", "--source", "{tmp}"],
    "bridge": ["serve", "--address", "tcp://127.0.0.1:*"],
    "ros": ["import", "--source", "{tmp}/cable"],  # a bag folder there: see below
    "view": ["control", "--goal", "{tmp}/goal.npy", "--record", "{tmp}/run.rrd"],
    "tensorboard": None,
}


def test_every_extra_has_a_command_that_needs_it_tried() -> None:
    assert set(NEEDS) == set(EXTRAS)


@pytest.mark.parametrize("extra", [name for name, argv in NEEDS.items() if argv is not None])
def test_a_missing_extra_is_named_in_one_line(extra: str, tmp_path: Path) -> None:
    """The extra's module hidden (as if never installed): one line naming the extra, exit 2,
    nothing written."""
    out = tmp_path / "out"
    bag = tmp_path / "cable" / "train" / "0"  # a ROS 2 bag folder, as `dlo import` sees one
    bag.mkdir(parents=True)
    (bag / "metadata.yaml").touch()
    argv = [arg.format(tmp=tmp_path) for arg in NEEDS[extra]]
    argv += [] if argv[0] == "serve" else ["--out", str(out)]  # serve writes nothing
    program = (
        f"import sys; sys.modules[{EXTRAS[extra]!r}] = None\n"
        f"sys.argv = ['dlo', *{argv!r}]\n"
        "from dlocli.cli import main; main()\n"
    )
    hint = f"pip install -c constraints.txt torch==2.13.0 -e '.[{extra}]'"
    assert hint in one_line_refusal(program)
    assert not out.exists()


def test_a_mujoco4_install_broken_by_mujoco3_is_named_in_one_line(tmp_path: Path) -> None:
    """pip upgrading an environment that had MuJoCo 3 to the pinned MuJoCo 4 removes files of
    mujoco-core, and `import mujoco` fails naming it (MuJoCo 4.0.1's message, stood in for here
    by a package that fails the same way): one line with the repair, exit 2, nothing written."""
    broken = tmp_path / "site" / "mujoco"
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text(
        "raise ImportError(\"The 'mujoco' package is installed, but its core bindings "
        "('mujoco-core') are missing or corrupted\")\n"
    )
    out = tmp_path / "goal.npy"
    program = (
        f"import sys; sys.path.insert(0, {str(broken.parent)!r})\n"
        f"sys.argv = ['dlo', 'goal', '--out', {str(out)!r}]\n"
        "from dlocli.cli import main; main()\n"
    )
    line = one_line_refusal(program)
    assert "pip install --force-reinstall --no-deps mujoco==" in line
    assert "mujoco-core==" in line
    assert not out.exists()


def one_line_refusal(program: str) -> str:
    """Run the Python ``program`` (the `dlo` entry point with an install fault): it must end
    with exit 2 and one line on stderr, which is returned."""
    result = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def test_ci_tries_every_extra_installed_alone() -> None:
    """.ci/extras names the feature tests of each extra (an extra added later must be too)."""
    script = (ROOT / ".ci" / "extras").read_text(encoding="utf-8")
    assert set(re.findall(r"^\s+\[([a-z0-9-]+)\]=", script, re.MULTILINE)) == set(EXTRAS)
