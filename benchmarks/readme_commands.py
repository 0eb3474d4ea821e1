"""The README's two commands on a fresh machine, read from the README itself, so CI and the
README cannot drift apart.

    python benchmarks/readme_commands.py install|main|short-main|test

prints one shell line: the install part of the first command, its run part, that run with its
counts cut to seconds (CI's check that the main job starts and finishes), or the whole test
command. The README must hold exactly one indented `pip install ...` line without pytest (the
main job) and one with it (the tests), under "Two commands on a fresh machine"; a count flag
this script does not know how to cut is an error, never silently a long run.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
SECTION = "## Two commands on a fresh machine"
#: count flags of the main command and the value CI runs them at
CUTS = {"--iters": "1", "--trials": "2", "--steps": "20", "--epochs": "1",
        "--initial-episodes": "2"}  # fmt: skip
#: numeric flags that are not counts: kept as written
NOT_COUNTS = {"--lr", "--seed"}


def commands(readme: Path = README) -> tuple[str, str]:
    """(main, test): the section's two indented `pip install` lines."""
    text = readme.read_text(encoding="utf-8")
    if SECTION not in text:
        raise SystemExit(f"{readme} has no '{SECTION}' section")
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    lines = [m.strip() for m in re.findall(r"^ {4}(pip install .+)$", section, re.MULTILINE)]
    main = [line for line in lines if "pytest" not in line]
    test = [line for line in lines if "pytest" in line]
    if len(main) != 1 or len(test) != 1:
        raise SystemExit(f"'{SECTION}' must hold one main and one test command; found {lines}")
    return main[0], test[0]


def split_main(main: str) -> tuple[str, str]:
    """(install, run) of the main command: the parts before and after its first `&&`."""
    install, sep, run = main.partition(" && ")
    if not sep or not run.startswith("dlo "):
        raise SystemExit(f"the main command is not `pip install ... && dlo ...`: {main}")
    return install, run


def shortened(run: str) -> str:
    """``run`` with every count cut to CUTS."""
    words = shlex.split(run)
    for index, word in enumerate(words[:-1]):
        value = words[index + 1]
        if not word.startswith("--") or not re.fullmatch(r"[0-9.e+-]+", value):
            continue
        if word in CUTS:
            words[index + 1] = CUTS[word]
        elif word not in NOT_COUNTS:
            raise SystemExit(f"the main command's {word} {value}: add it to CUTS or NOT_COUNTS")
    return shlex.join(words)


def main() -> None:
    what = sys.argv[1] if len(sys.argv) == 2 else ""
    main_command, test_command = commands()
    install, run = split_main(main_command)
    lines = {"install": install, "main": run, "short-main": shortened(run), "test": test_command}
    if what not in lines:
        raise SystemExit(f"usage: {sys.argv[0]} {'|'.join(lines)}")
    print(lines[what])


if __name__ == "__main__":
    main()
