"""Every number a results table of the documentation (and the README) quotes comes from the
committed result file the table names, so a number cannot drift from its file.

A table with a decimal number outside its first column names its sources in an HTML comment
on the line before it (invisible on the site and on GitHub):

    <!-- numbers: examples/bench_paper/summary.md benchmarks/results/rod_physics.txt -->

and each number of its cells (but the first column's, which names the row, and a column named
by `skip:N`, 1 the first, e.g. closed-form references) must be one of the sources' numbers as
printed there or rounded to the digits the table shows (of a Markdown source, the numbers of
its tables, not of its prose). A table that
quotes no result says why instead (`<!-- numbers: none, ... -->`). The paper's main table is
also checked cell by cell against its bench summary."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: the pages whose tables are checked: the README's and the site's
PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
ANNOTATION = re.compile(r"^<!-- numbers: (.+?) -->$")
NUMBER = re.compile(r"(?<![\w.])\d+(?:,\d{3})*(?:\.\d+)?(?:e[+-]?\d+)?", re.IGNORECASE)
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+")


def tables(page: Path) -> list[tuple[int, str, list[list[str]]]]:
    """(line number, the annotation before it or '', body rows as cells) of each table."""
    lines = page.read_text(encoding="utf-8").splitlines()
    found, index = [], 0
    while index < len(lines):
        if not lines[index].lstrip().startswith("|"):
            index += 1
            continue
        start = index
        while index < len(lines) and lines[index].lstrip().startswith("|"):
            index += 1
        before = [line.strip() for line in lines[:start] if line.strip()]
        annotation = before[-1] if before and ANNOTATION.match(before[-1]) else ""
        rows = [
            [cell.strip() for cell in row.strip().strip("|").split("|")]
            for row in lines[start + 2 : index]
        ]
        found.append((start + 1, annotation, rows))
    return found


def numbers(text: str) -> list[str]:
    """The numbers of ``text`` as written (a thousands comma dropped, any sign ignored)."""
    plain = text.replace("*", "").replace("−", "-")
    return [match.replace(",", "") for match in NUMBER.findall(plain)]


def _source_values(paths: list[str]) -> list[float]:
    values = []
    for path in paths:
        text = (ROOT / path).read_text(encoding="utf-8")
        if path.endswith(".md"):  # a Markdown result: its tables, not its prose
            text = "\n".join(line for line in text.splitlines() if line.lstrip().startswith("|"))
        values.extend(float(n) for n in numbers(text))
    return values


def _matches(quoted: str, values: list[float]) -> bool:
    """``quoted`` is one of ``values`` rounded to the digits it shows."""
    q = float(quoted)
    if "e" in quoted.lower():
        mantissa = quoted.lower().split("e")[0]
        digits = len(mantissa.split(".")[1]) if "." in mantissa else 0
        half = 0.5 * 10 ** (int(quoted.lower().split("e")[1]) - digits)
    else:
        digits = len(quoted.split(".")[1]) if "." in quoted else 0
        half = 0.5 * 10**-digits
    return any(abs(abs(v) - q) <= half * (1 + 1e-9) for v in values)


def annotated_tables() -> list[tuple[str, int, list[str], list[list[str]]]]:
    found = []
    for page in PAGES:
        for line, annotation, rows in tables(page):
            sources = ANNOTATION.match(annotation).group(1) if annotation else ""
            if sources and not sources.startswith("none"):
                words = sources.split()
                skip = {int(w[5:]) - 1 for w in words if w.startswith("skip:")} | {0}
                kept = [[c for i, c in enumerate(row) if i not in skip] for row in rows]
                found.append((page.name, line, [w for w in words if ":" not in w], kept))
    return found


def test_every_table_with_decimals_names_its_source_or_why_it_has_none() -> None:
    missing = []
    for page in PAGES:
        for line, annotation, rows in tables(page):
            quoted = any(DECIMAL.search(" ".join(row[1:])) for row in rows)
            if quoted and not annotation:
                missing.append(f"{page.name}:{line}")
    assert not missing, f"tables quoting numbers without a <!-- numbers: ... --> line: {missing}"
    assert len(annotated_tables()) >= 9


@pytest.mark.parametrize(
    "page, line, sources, rows",
    annotated_tables(),
    ids=lambda v: str(v) if isinstance(v, (str, int)) else "",
)
def test_each_quoted_number_is_its_result_files(page: str, line: int, sources, rows) -> None:
    for path in sources:
        assert (ROOT / path).is_file(), f"{page}:{line} names {path}, which is not there"
    values = _source_values(sources)
    stray = [
        f"{row}: {quoted}"
        for row in rows
        for cell in row
        for quoted in numbers(cell)
        if not _matches(quoted, values)
    ]
    assert not stray, f"{page}:{line}: numbers not in {sources}: {stray}"


def _summary_rows(path: Path) -> dict[tuple[str, str], list[str]]:
    """(agent, evaluated on) -> the bench summary's cells."""
    rows = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 10 and cells[3].isdigit():
            rows[(cells[0], cells[2])] = cells
    return rows


def test_the_papers_table_is_its_bench_summary_cell_by_cell() -> None:
    """Score, final and initial error, random goals' and bimanual scores of each agent."""
    summary = _summary_rows(ROOT / "examples/bench_paper/summary.md")
    page = DOCS / "results.md"
    ((_, _, rows),) = [t for t in tables(page) if t[2] and t[2][0][0] == "`zero`"]
    for row in rows:
        agent = row[0].strip("`")
        own = summary[(agent, "single, fixed goal")]
        assert row[1:6] == [own[3], own[4], own[5], own[7], own[6]], agent
        assert row[7] == summary[(agent, "single, random goals")][5], agent
        bimanual = summary.get((agent, "bimanual, fixed goal"))
        assert row[8] == (bimanual[5] if bimanual else "– (6-D policy)"), agent


@pytest.mark.parametrize(
    "run",
    [
        "online_paper",
        "online_paper_flex",
        "online_paper_flex_servo",
        "online_paper_flex_servo_above",
        "online_paper_flex_rest_roll",
    ],
)
def test_a_paper_scale_runs_table_is_its_metrics(run: str) -> None:
    """The table of examples/RUN/README.md is what report.py prints from the run's files."""
    import runpy

    report = runpy.run_path(str(ROOT / "examples" / "online_paper" / "report.py"))
    rows = report["table"](ROOT / "examples" / run).splitlines()[2:]
    readme = (ROOT / "examples" / run / "README.md").read_text(encoding="utf-8").splitlines()
    quoted = [line for line in readme if re.match(r"^\| \d+ \| [\d,]+ \|", line)]
    assert quoted == rows
