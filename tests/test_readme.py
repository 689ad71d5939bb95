"""The README matches the tree: its "What is where" names every module of the package and every launcher, and
names no file that does not exist; its links into BUILD_NOTES.md land on headings that exist."""

import glob
import os
import re

from helpers import ROOT, readme_section


def _read(name):
    with open(os.path.join(ROOT, name), encoding="utf-8") as f:
        return f.read()


def test_what_is_where_lists_every_module_and_launcher_and_nothing_else():
    where = readme_section("What is where")
    named = set(re.findall(r"`([\w/]+\.py)`", where))
    package = os.path.join(ROOT, "e2e_percep_jax")
    modules = {
        os.path.relpath(p, package)
        for p in glob.glob(os.path.join(package, "**", "*.py"), recursive=True)
        if os.path.basename(p) != "__init__.py"
    }
    launchers = {os.path.basename(p) for p in glob.glob(os.path.join(ROOT, "experiments", "*.py"))}
    experiments_row = next(line for line in where.splitlines() if line.startswith("| `experiments/`"))
    assert modules - named == set(), "modules missing from the README's What is where"
    assert {n for n in launchers if f"`{n}`" not in experiments_row} == set(), "launchers missing there"
    assert named - modules - launchers == set(), "files named there that do not exist"


def _anchor(heading):
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_links_into_the_build_notes_land_on_headings():
    headings = re.findall(r"^#+ (.+)$", _read("BUILD_NOTES.md"), flags=re.MULTILINE)
    anchors = {_anchor(h) for h in headings}
    links = re.findall(r"\(BUILD_NOTES\.md#([^)]+)\)", _read("README.md"))
    assert links and [a for a in links if a not in anchors] == []
