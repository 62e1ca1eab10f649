"""Figures in the docs come from results JSON: every generated block (``<!-- bench:KIND
FILES[@COMMIT] -->`` ... ``<!-- /bench -->``) in README.md, docs/*.md and bench/README.md is
exactly what ``python -m bench --table`` prints from ``bench/results`` (at the named git
commit); the design the code cites is the project's own (docs/METHOD.md), with every cited
section present."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import tables  # noqa: E402
from bench.provenance import git  # noqa: E402


def _all_blocks() -> list[tuple[Path, str, list[str], str | None, str]]:
    out = []
    for path in tables.doc_files():
        for kind, files, at, body in tables.blocks(path.read_text()):
            out.append((path, kind, files, at, body))
    return out


def test_the_measured_tables_of_the_docs_are_generated() -> None:
    where = {(p.name, k) for p, k, _f, _a, _b in _all_blocks()}
    assert {("SERVICES.md", "services"), ("ATLAS.md", "atlas")} <= where


@pytest.mark.parametrize(
    "path,kind,files,at,body",
    _all_blocks(),
    ids=lambda v: v.name if isinstance(v, Path) else None,
)
def test_every_generated_block_is_what_the_json_gives(
    path: Path, kind: str, files: list[str], at: str | None, body: str
) -> None:
    if at is not None and not git("rev-parse", "--verify", "--quiet", f"{at}^{{commit}}"):
        if git("rev-parse", "--is-shallow-repository") == "true":
            pytest.skip(f"shallow clone: commit {at} not available")
        raise AssertionError(f"{path.name}: block cites commit {at}, not in the repository")
    want = tables.render(kind, files, at)
    assert body == want, (
        f"{path.relative_to(ROOT)}: the bench:{kind} block differs from its JSON; run "
        "`python -m bench --refresh-docs`"
    )


def test_a_changed_figure_is_caught_and_refreshed(tmp_path: Path) -> None:
    """A block whose figure was edited by hand differs from the JSON's; ``refresh`` (what
    ``python -m bench --refresh-docs`` runs) puts the JSON's figure back."""
    want = tables.render("services", ["services.json"], None)
    doctored = want.replace("| 0 |", "| 7 |", 1)
    assert doctored != want
    doc = tmp_path / "DOC.md"
    head = "text\n<!-- bench:services services.json -->\n"
    doc.write_text(f"{head}{doctored}<!-- /bench -->\n")
    [(_kind, _files, _at, body)] = list(tables.blocks(doc.read_text()))
    assert body == doctored != tables.render("services", ["services.json"], None)
    assert tables.refresh(doc)
    assert doc.read_text() == f"{head}{want}<!-- /bench -->\n"
    assert not tables.refresh(doc)


def test_table_cli_prints_the_block_and_refuses_unknown_tables() -> None:
    run = [sys.executable, "-m", "bench", "--table"]
    res = subprocess.run(
        [*run, "services", "services.json", "--at", "dbf23e2"],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    if res.returncode == 0:
        assert res.stdout == tables.render("services", ["services.json"], "dbf23e2")
        assert "| 1 | - | 100 | 5000 | 1.72 | 4.40 | 0 | 0 / 50000 | 104 % | - |" in res.stdout
    else:
        assert "no bench/results/services.json at commit dbf23e2" in res.stderr
    bad = subprocess.run(
        [*run, "nosuch", "services.json"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "unknown table 'nosuch'" in bad.stderr
    missing = subprocess.run(
        [*run, "services", "nosuch.json"], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert missing.returncode == 2 and "no results file" in missing.stderr


SOURCES = ("confnav", "services", "schemas", "bench", "tests", "docs")


def _texts() -> list[tuple[Path, str]]:
    out = []
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix in (".py", ".md") and path.is_file() and "results" not in path.parts:
                out.append((path, path.read_text(errors="replace")))
    out.append((ROOT / "README.md", (ROOT / "README.md").read_text()))
    # generated blocks quote the results files' own strings: the prose is what is checked
    return [(p, tables.BLOCK.sub("", text)) for p, text in out]


def test_no_citation_of_a_design_file_outside_the_repository() -> None:
    here = Path(__file__).resolve()
    cited = [
        f"{p.relative_to(ROOT)}:{i}"
        for p, text in _texts()
        if p != here
        for i, line in enumerate(text.splitlines(), 1)
        if "DESIGN.md" in line
    ]
    assert not cited, cited


def test_every_cited_method_section_exists() -> None:
    method = (ROOT / "docs" / "METHOD.md").read_text()
    sections = {int(m[1]) for m in re.finditer(r"^## (\d+)\. ", method, re.M)}
    assert sections == {1, 2, 3, 4, 5, 6}
    cite = re.compile(r"docs/METHOD\.md\s+(?:sec\.|section)\s+(\d+)")
    seen = [(p, int(m[1])) for p, text in _texts() for m in cite.finditer(text)]
    assert len(seen) >= 28  # the code's former DESIGN.md citations
    missing = [f"{p.relative_to(ROOT)}: section {n}" for p, n in seen if n not in sections]
    assert not missing, missing
