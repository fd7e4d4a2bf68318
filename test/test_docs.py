"""The docs against the code: docs/architecture.md lists every module, and every doc heading the
code cites exists in a reference doc (code never cites the dated journal, docs/journal/)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
ARCHITECTURE_DOC = DOCS / "architecture.md"
PACKAGES = {
    "hdmap_core": ROOT / "src" / "hdmap_core" / "hdmap_core",
    "hdmap_ros": ROOT / "src" / "hdmap_ros" / "hdmap_ros",
}
# Where code may cite docs: the packages, the scripts, the tests.
CITING = [ROOT / "src", ROOT / "scripts", ROOT / "test"]


def _documented_modules(text: str) -> set[str]:
    """Module paths of the tables in architecture.md: a row's first cell is a path relative to the
    package named by the last heading that names one (``## `hdmap_core` ...``)."""
    documented = set()
    package = None
    for line in text.splitlines():
        heading = re.match(r"^#+ .*`(hdmap_core|hdmap_ros)[`/]", line)
        if heading:
            package = heading.group(1)
            continue
        row = re.match(r"^\|\s*`([\w/]+\.py)`", line)
        if row and package:
            documented.add(f"{package}/{row.group(1)}")
    return documented


def test_architecture_doc_lists_every_module() -> None:
    expected = {
        f"{package}/{path.relative_to(folder).as_posix()}"
        for package, folder in PACKAGES.items()
        for path in folder.rglob("*.py")
        if path.name != "__init__.py"
    }
    documented = _documented_modules(ARCHITECTURE_DOC.read_text())
    missing = sorted(expected - documented)
    gone = sorted(documented - expected)
    assert not missing and not gone, (
        f"docs/architecture.md: add a row for each module missing from its package's tables: {missing}; "
        f"remove rows of modules that no longer exist: {gone}"
    )


def _citations() -> list[tuple[Path, str, str | None]]:
    """(file, doc path, quoted heading or None) of every ``docs/<name>.md`` a source file names.
    A heading is the quoted text right after the path (``docs/graph.md, "Side steps"``); comment
    markers of a citation wrapped over lines are joined first."""
    found = []
    for base in CITING:
        for path in sorted(base.rglob("*.py")):
            text = re.sub(r"\n\s*#\s*", " ", path.read_text())
            text = re.sub(r"\s+", " ", text)
            for m in re.finditer(r"docs/([\w/.-]+\.md)(?:[,:]? ?\(?\s*\"([^\"]+)\")?", text):
                found.append((path, m.group(1), m.group(2)))
    return found


def _headings(doc: Path) -> list[str]:
    return [m.group(1).strip().lower() for m in re.finditer(r"^#+ (.*)$", doc.read_text(), flags=re.M)]


def test_the_citation_scan_finds_citations() -> None:
    # Guards the test below against passing on a scan that finds nothing.
    assert any(doc == "pipeline.md" and heading for _, doc, heading in _citations())


def test_code_cites_only_reference_docs_and_existing_headings() -> None:
    wrong = []
    for path, doc, heading in _citations():
        where = path.relative_to(ROOT)
        target = DOCS / doc
        if doc.startswith("journal/"):
            wrong.append(f"{where}: cites the journal ({doc}); cite the reference doc that states the rule")
        elif not target.exists():
            wrong.append(f"{where}: docs/{doc} does not exist")
        elif heading and not any(h.startswith(heading.strip().lower()) for h in _headings(target)):
            wrong.append(f'{where}: docs/{doc} has no heading "{heading}"')
    assert not wrong, "\n".join(wrong)
