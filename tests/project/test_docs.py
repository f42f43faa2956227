"""The documentation stays true and navigable.

- every page under docs/ is linked from docs/README.md (the index);
- every relative link of docs/ and of the README names a file or folder that exists;
- the command-line reference's generated blocks (docs/interfaces/cli.md) are what the parser
  prints (``python -m sarship.docs_cli`` regenerates them);
- every ``SARSHIP_*`` environment variable the code reads is named somewhere in the docs.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
#: Markdown links ``[text](target)`` and reference definitions ``[id]: target``.
LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)|^\s*\[[^\]]+\]:\s*(\S+)", re.M)
CODE = re.compile(r"```.*?```|`[^`\n]*`", re.S)


def links(md: Path) -> list[str]:
    """The link targets of a Markdown page, leaving out code spans and fenced blocks."""
    text = CODE.sub("", md.read_text(encoding="utf-8"))
    return [a or b for a, b in LINK.findall(text)]


def local_target(md: Path, target: str) -> Path | None:
    """The file a relative link of ``md`` names (anchor dropped), or None for an external link
    (``http:``, ``mailto:``, ...) or a link to an anchor of the same page."""
    if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("#"):
        return None
    path = unquote(target.split("#", 1)[0].split("?", 1)[0])
    return (md.parent / path).resolve()


def pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def test_every_docs_page_is_linked_from_the_index():
    """docs/README.md is the index: it links every page of docs/ itself (issue 30: 8 of 21 were
    reachable only through other pages, or not at all)."""
    index = DOCS / "README.md"
    linked = {p for t in links(index) if (p := local_target(index, t)) is not None}
    unlinked = [str(p.relative_to(DOCS)) for p in pages() if p != index and p.resolve() not in linked]
    assert not unlinked, f"pages of docs/ that docs/README.md does not link: {unlinked} (add them to the index)"


@pytest.mark.parametrize("md", [REPO / "README.md", *pages()], ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(md):
    broken = [t for t in links(md) if (p := local_target(md, t)) is not None and not p.exists()]
    assert not broken, f"{md.relative_to(REPO)} links to paths that do not exist: {broken}"


@pytest.mark.skipif(
    sys.version_info[:2] != (3, 11),
    reason="the page is generated with Python 3.11 (CI's); argparse lays help out differently in other versions",
)
def test_cli_reference_is_generated_from_the_parser():
    from sarship.docs_cli import PAGE, REGENERATE, help_texts, rewrite

    page = (REPO / PAGE).read_text(encoding="utf-8")
    texts = help_texts()
    assert rewrite(page, texts) == page, (
        f"{PAGE} differs from `sarship ... --help`: run `{REGENERATE}` in the repository and commit the page"
    )
    # every command has its block, so that a new option or setting cannot stay undocumented
    for cmd in texts:
        assert f"<!-- BEGIN GENERATED: {cmd} --help -->" in page, cmd


def test_cli_reference_generator_rewrites_only_its_blocks():
    from sarship.docs_cli import block, rewrite

    texts = {"sarship": "usage: sarship\n", "sarship new": "usage: sarship new\n"}
    page = (
        "# title\n\nprose\n\n"
        + block("sarship", "usage: old\n")
        + "\n\nmore prose\n\n"
        + block("sarship gone", "usage: gone\n")
        + "\n"
    )
    out = rewrite(page, texts)
    assert out.startswith("# title\n\nprose\n\n" + block("sarship", "usage: sarship\n") + "\n\nmore prose\n")
    assert "gone" not in out  # a command the parser no longer has loses its block
    assert out.rstrip().endswith("## `sarship new`\n\n" + block("sarship new", "usage: sarship new\n"))
    assert rewrite(out, texts) == out


def test_every_environment_setting_is_documented():
    code = "\n".join(
        p.read_text(encoding="utf-8")
        for folder in ("pipeline", "workers", "service", "sarship")
        for p in (REPO / folder).rglob("*.py")
    )
    names = set(re.findall(r"\bSARSHIP_[A-Z0-9][A-Z0-9_]*[A-Z0-9]\b", code))
    from sarship.service.settings import Settings

    names |= {f"SARSHIP_{n.upper()}" for n in Settings.model_fields}
    docs = "\n".join(
        p.read_text(encoding="utf-8") for p in [*pages(), REPO / "README.md", REPO / "deploy" / "README.md"]
    )
    missing = sorted(n for n in names if not re.search(rf"\b{n}\b", docs))
    assert not missing, f"environment variables the code reads that no page of docs/ names: {missing}"
