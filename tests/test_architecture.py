"""ARCHITECTURE.md stays true: every module, package and file it names exists, it names
every package of dlocli, and it fits on one screen."""

from __future__ import annotations

from test_layout import DOTTED, REPO_PATH, ROOT, broken_citations

ARCHITECTURE = ROOT.parent / "ARCHITECTURE.md"
#: one screen
MAX_LINES = 60


def test_every_path_it_names_exists():
    text = ARCHITECTURE.read_text()
    named = len(REPO_PATH.findall(text)) + len(DOTTED.findall(text))
    assert named >= 30, "the check would be vacuous: ARCHITECTURE.md names few paths"
    assert not broken_citations(ARCHITECTURE)


def test_it_names_every_package():
    text = ARCHITECTURE.read_text()
    packages = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))
    missing = [name for name in packages if f"dlocli/{name}/" not in text]
    assert not missing, f"ARCHITECTURE.md says nothing of dlocli/{missing[0]}/: add its room"


def test_it_fits_on_one_screen():
    assert len(ARCHITECTURE.read_text().splitlines()) <= MAX_LINES
