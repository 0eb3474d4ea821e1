"""The public API a notebook uses: `import dlocli` stays cheap, and the notebook snippet of
docs/python.md runs as written and prints plain-float scores with their references."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import dlocli

PAGE = Path(__file__).resolve().parents[1] / "docs" / "python.md"


def notebook_snippet() -> str:
    blocks = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)
    return next(block for block in blocks if "random_dataset" in block)


def test_import_dlocli_loads_no_torch_or_simulator():
    heavy = ("torch", "mujoco", "pybullet")
    script = f"import sys, dlocli\nprint([m for m in {heavy!r} if m in sys.modules])"
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


def test_every_public_name_resolves():
    for name in dlocli.__all__:
        assert getattr(dlocli, name) is not None, name
    assert set(dlocli.__all__) <= set(dir(dlocli))


def test_the_pages_notebook_snippet_runs(capsys):
    exec(compile(notebook_snippet(), str(PAGE), "exec"), {})
    lines = capsys.readouterr().out.strip().splitlines()
    scores = {line.split(" ", 1)[0]: ast.literal_eval(line.split(" ", 1)[1]) for line in lines}
    assert sorted(scores) == ["mpc", "random", "zero"]
    for result in scores.values():  # literal_eval refused np.float64(...): plain floats
        assert all(type(v) is float for v in result.values()), result
    initial = {result["initial_error_mm"] for result in scores.values()}
    assert len(initial) == 1, "the references start where the MPC episode starts"
