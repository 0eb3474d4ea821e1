"""`import dlocli` and every command's `--help` stay light, and the imports inside functions
that keep them light are the only ones: each is listed below with its reason."""

from __future__ import annotations

import ast
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

from test_layout import ROOT, _type_checking_block, module_name

#: what `import dlocli` and `dlo COMMAND --help` never load (numpy, pydantic, typer and
#: gymnasium's core, spaces and registration they do load)
HEAVY = [
    "torch", "mujoco", "pybullet", "stable_baselines3", "matplotlib", "ray", "h5py",
    "scipy", "numba", "minari", "tensorboard",
]  # fmt: skip

_REPORT = (
    "import sys\n"
    f"heavy = [m for m in {HEAVY!r} if m in sys.modules]\n"
    "envs = [m for m in sys.modules if m.startswith('gymnasium.envs.')"
    " and m != 'gymnasium.envs.registration']\n"
    "print('LOADED', heavy + envs)\n"
)


def _help_script(argv: list[str]) -> str:
    return (
        "import contextlib, io, runpy, sys\n"
        f"sys.argv = ['dlo', *{argv!r}]\n"
        "with contextlib.redirect_stdout(io.StringIO()) as shown:\n"
        "    try:\n        runpy.run_module('dlocli', run_name='__main__')\n"
        "    except SystemExit as exit:\n        assert exit.code in (0, None), exit.code\n"
        "print(shown.getvalue())\n" + _REPORT
    )


def _run(script: str) -> str:
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


def _loaded(stdout: str) -> str:
    return stdout.strip().splitlines()[-1]


def _commands(help_text: str) -> list[str]:
    lines = help_text.split("Commands:", 1)[1].splitlines()
    return [line.split()[0] for line in lines if line.startswith("  ") and line.split()]


def test_import_dlocli_and_every_help_load_no_heavy_library():
    """One interpreter per case: `import dlocli`, `dlo --help`, and `dlo COMMAND --help` for
    each command `dlo --help` lists."""
    top = _run(_help_script(["--help"]))
    commands = _commands(top)
    assert {"train", "online", "bench"} <= set(commands), commands
    scripts = {"import dlocli": "import dlocli\n" + _REPORT, "--help": _help_script(["--help"])}
    scripts |= {f"{c} --help": _help_script([c, "--help"]) for c in commands}
    with ThreadPoolExecutor(max_workers=4) as pool:
        loaded = dict(
            zip(scripts, pool.map(lambda s: _loaded(_run(s)), scripts.values()), strict=True)
        )
    assert all(line == "LOADED []" for line in loaded.values()), {
        case: line for case, line in loaded.items() if line != "LOADED []"
    }


# ------------------------------------------------------------------ imports inside functions
_CLI_RUNNER = "the command's runner imports torch; `dlo COMMAND --help` must not"
_CONTROL = "torch; on the `dlo control --help` path"
_TORCH = "imports torch, and this module is on the `dlo online --help` path (dlocli.runs.online)"

#: (module, dlocli module it imports inside a function) -> why the import waits for the call;
#: any other dlocli import belongs at module level
LAZY_IMPORTS = {
    # the public namespace and the `dlo` entry point: imported on first use by design
    ("dlocli", "dlocli.registry"): "`import dlocli` loads names on first access (PEP 562)",
    ("dlocli", "dlocli.env.registration"): "Gymnasium ids registered without importing specs",
    ("dlocli.cli", "dlocli.cli.flags"): "`dlo --help` and `dlo --version` load no flag module",
    # a command's module is loaded for its --help; its torch-importing runner waits for the run
    ("dlocli.cli.bench", "dlocli.bench.run"): _CLI_RUNNER,
    ("dlocli.cli.bench", "dlocli.bench.report"): _CLI_RUNNER,
    ("dlocli.cli.adapt", "dlocli.runs.adapt"): _CLI_RUNNER,
    ("dlocli.cli.eval", "dlocli.runs.evaluate"): _CLI_RUNNER,
    ("dlocli.cli.train", "dlocli.models.fitting"): _CLI_RUNNER,
    ("dlocli.cli.train", "dlocli.runs.train"): _CLI_RUNNER,
    ("dlocli.cli.track", "dlocli.runs.track"): "scipy; `dlo track --help` needs only the spec",
    ("dlocli.cli.sample", "dlocli.runs.sample"): "the simulator; `dlo sample --help` needs only "
    "the spec",
    # `dlo online --help` and `dlo control --help` load these modules' specs
    ("dlocli.runs.control", "dlocli.models.base"): "torch; on the `dlo control --help` path",
    ("dlocli.runs.control", "dlocli.models.checkpoints"): "torch; on the `dlo control --help` path",
    ("dlocli.runs.control_code", "dlocli.models.code_follow"): _CONTROL,
    ("dlocli.runs.control_code", "dlocli.models.code_pick"): _CONTROL,
    ("dlocli.runs.online.loop", "dlocli.models.base"): _TORCH,
    ("dlocli.runs.online.loop", "dlocli.models.fitting"): _TORCH,
    ("dlocli.runs.online.loop", "dlocli.models.update_steps"): _TORCH,
    ("dlocli.runs.online.loop", "dlocli.models.checkpoints"): _TORCH,
    ("dlocli.runs.online.loop", "dlocli.runs.online.marker_update"): _TORCH,
    ("dlocli.runs.online.results", "dlocli.models.checkpoints"): _TORCH,
    ("dlocli.runs.online.run", "dlocli.models.base"): _TORCH,
    ("dlocli.runs.online.trials", "dlocli.models.checkpoints"): _TORCH,
    ("dlocli.plots", "dlocli.models.evaluation"): (
        "torch, only for a model's rollout figure; the bench and control figures need none"
    ),
    # an optional library, only for a fallback
    ("dlocli.backends.pybullet_chain", "dlocli.backends.render"): (
        "matplotlib, only when PyBullet cannot render"
    ),
}


def function_level_imports() -> dict[tuple[str, str], list[str]]:
    """(module, imported dlocli module) -> where, for each dlocli import inside a function."""
    modules = {module_name(p) for p in ROOT.rglob("*.py")}
    found: dict[tuple[str, str], list[str]] = {}
    for path in sorted(ROOT.rglob("*.py")):
        tree = ast.parse(path.read_text())
        skip = {id(n) for b in ast.walk(tree) if _type_checking_block(b) for n in ast.walk(b)}
        functions = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.Lambda)]
        functions += [n for n in ast.walk(tree) if isinstance(n, ast.AsyncFunctionDef)]
        for function in functions:
            for node in ast.walk(function):
                if id(node) in skip:
                    continue
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    sub = [f"{node.module}.{alias.name}" for alias in node.names]
                    names = [n for n in sub if n in modules] or [node.module]
                else:
                    continue
                for name in names:
                    if name.split(".")[0] == "dlocli":
                        where = f"{path.relative_to(ROOT.parent)}:{node.lineno}"
                        found.setdefault((module_name(path), name), []).append(where)
    return found


def test_imports_inside_functions_are_only_the_listed_ones():
    """A dlocli import inside a function is listed in LAZY_IMPORTS with its reason (it keeps
    `import dlocli` or a `--help` from loading a heavy library); every other goes at the top
    of its module. A listed import that no longer exists is dropped from the list."""
    found = function_level_imports()
    unlisted = {key: where for key, where in found.items() if key not in LAZY_IMPORTS}
    assert not unlisted, f"move these imports to module level, or list them: {unlisted}"
    stale = sorted(set(LAZY_IMPORTS) - set(found))
    assert not stale, f"no longer imported inside a function: {stale}"


def test_the_scan_sees_an_import_inside_a_function():
    found = function_level_imports()
    assert ("dlocli.runs.online.loop", "dlocli.models.base") in found
    assert ("dlocli.runs.online.loop", "dlocli.data") not in found  # at module level
