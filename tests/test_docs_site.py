"""The documentation site: its generated reference pages are fresh, and no section of the old README was lost.

The site itself is built by CI (``mkdocs build --strict`` in ``.ci/run``), which fails on a broken
link or a page neither in the navigation nor listed as outside it.
"""

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# The `##` section titles of README.md before the documentation site (commit cd6a072): each must be a heading of a
# page of the site, so the text the README had under it has a home.
OLD_README_SECTIONS = (
    "Using the envs",
    "Training CIG-TD3 (COIN) and ITD3",
    "TraCo (re-implemented TD3 baseline)",
    "PPO baselines (IPPO, CPPO, MFPO, CoPO)",
    "The arena: navigation and parking (seed-2 paper)",
    "Sweeps: seeds, ablations, generalization (Ray Tune)",
    "Evaluation protocol and report",
    "Running on a cluster",
    "Exporting policies",
    "MetaDrive backend (optional)",
    "Scenarios",
    "Observation (91 floats in [0, 1], MetaDrive's `LidarStateObservation`)",
    "Action and vehicle",
    "Reward, termination tests and global reward",
    "Metrics (`coin_app/evaluation/metrics.py`, usable without Ray)",
    "Heuristic driver",
    "Speed and fast training",
    "Deviations from MetaDrive",
    "Layout",
    "Development",
)
README_COMMANDS = (
    "python3.11 -m venv .venv && .venv/bin/pip install -q -r requirements.txt -e . && .venv/bin/python -m coin_app demo --out runs/demo",
    "python3.11 -m venv .venv && .venv/bin/pip install -q -r requirements.txt -e . && .venv/bin/python -m pytest -q tests",
)


def _generator():
    spec = importlib.util.spec_from_file_location("gen_reference", DOCS / "gen_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _site_pages() -> list[Path]:
    """The markdown pages of the site (the files mkdocs.yml's docs_dir holds)."""
    return sorted(DOCS.rglob("*.md"))


def _nav_pages() -> list[str]:
    """The pages named in mkdocs.yml's nav (read as text: no YAML parser needed)."""
    text = (ROOT / "mkdocs.yml").read_text().split("\nnav:\n", 1)[1]
    return re.findall(r":\s+(\S+\.md)\s*$", text, flags=re.MULTILINE)


def test_generated_reference_pages_are_those_the_code_gives():
    stale = [str(path.relative_to(ROOT)) for path, text in _generator().pages().items() if not path.exists() or path.read_text() != text]
    assert not stale, f"out of date with the code: {stale}; run python docs/gen_reference.py and commit the pages"


@pytest.mark.parametrize("title", OLD_README_SECTIONS)
def test_every_section_of_the_old_readme_is_a_heading_of_the_site(title):
    headings = {line.lstrip("#").strip() for page in _site_pages() for line in page.read_text().splitlines() if re.match(r"#{1,6} ", line)}
    assert title in headings, f"the old README's section {title!r} is no heading of any page under docs/"


def test_every_nav_entry_exists_and_the_readme_keeps_its_commands():
    missing = [page for page in _nav_pages() if not (DOCS / page).is_file()]
    assert not missing
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    for command in README_COMMANDS:
        assert command in readme.splitlines(), command
    assert README_COMMANDS[1] in (ROOT / ".ci" / "run").read_text().splitlines()


def test_no_absolute_machine_path_in_the_docs():
    pattern = re.compile(r"(?<![\w.:/])/(?:work|home|Users|tmp/(?!coin_app_site))[\w./-]*|[A-Za-z]:\\\\")
    hits = []
    for page in [ROOT / "README.md", *_site_pages()]:
        for n, line in enumerate(page.read_text().splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{page.relative_to(ROOT)}:{n}: {line.strip()[:80]}")
    assert not hits, hits


def test_every_test_the_reliability_page_names_exists():
    # docs/reliability.md states what a test checks: each test and test file it names must be there (renames go stale)
    text = (DOCS / "reliability.md").read_text()
    tests = {p.name: p.read_text() for p in (ROOT / "tests").glob("test_*.py")}
    named = set(re.findall(r"\b(test_\w+)\b", text))
    files = {n for n in named if f"{n}.py" in tests}
    missing = sorted(n for n in named - files if not any(re.search(rf"^def {n}\(", src, re.M) for src in tests.values()))
    assert len(named) > 40 and missing == []
    assert not [f for f in re.findall(r"tests/(\w+\.py)", text) if f not in tests]
