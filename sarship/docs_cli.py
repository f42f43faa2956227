"""The command-line reference of docs/interfaces/cli.md, generated from the parser.

Every ``sarship`` command's ``--help`` text (usage, options, and for ``serve`` every
``SARSHIP_*`` setting) is rendered from :func:`sarship.cli.build_parser` into the blocks of the
page marked ``<!-- BEGIN GENERATED: sarship CMD --help -->`` ... ``<!-- END GENERATED -->``; the
prose around the blocks is hand-written and left alone. Regenerate after changing an option::

    python -m sarship.docs_cli            # rewrites docs/interfaces/cli.md in place
    python -m sarship.docs_cli --check    # exit 1 when the page differs from the parser

``tests/project/test_docs.py`` runs the check. A command with no block yet gets a new section at the end
of the page (move it where it belongs; the generator keeps the block wherever it is).
"""

from __future__ import annotations

import argparse
import functools
import re
import sys
from pathlib import Path

#: Width of the rendered help (what a terminal of ``COLUMNS=100`` gives: argparse keeps two
#: columns free), so that the page does not depend on the terminal of whoever regenerates it.
WIDTH = 98
#: The page, relative to the repository root (the default of the command line).
PAGE = Path("docs") / "interfaces" / "cli.md"
#: The command that regenerates the page, quoted by the check's message.
REGENERATE = "python -m sarship.docs_cli"

_BLOCK = re.compile(r"<!-- BEGIN GENERATED: (?P<cmd>sarship(?: [a-z_-]+)?) --help -->\n.*?<!-- END GENERATED -->", re.S)


def _fixed_width(parser: argparse.ArgumentParser) -> None:
    """Render ``parser`` at :data:`WIDTH` columns, without colour, whatever the terminal."""
    parser.formatter_class = functools.partial(parser.formatter_class, width=WIDTH)
    if hasattr(parser, "color"):  # Python >= 3.14 colours help on a terminal
        parser.color = False


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The sub-parsers of ``parser`` by command name, in the order they were added.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A parser with one set of sub-commands (``sarship``'s).

    Returns
    -------
    dict of str to argparse.ArgumentParser
        Empty when ``parser`` has no sub-commands.
    """
    for action in parser._actions:  # argparse has no public accessor for its sub-parsers
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def help_texts(parser: argparse.ArgumentParser | None = None) -> dict[str, str]:
    """Every command's ``--help`` text, at :data:`WIDTH` columns.

    Parameters
    ----------
    parser : argparse.ArgumentParser, optional
        The top-level parser (default: :func:`sarship.cli.build_parser`'s).

    Returns
    -------
    dict of str to str
        ``"sarship"`` and ``"sarship CMD"`` for every sub-command, to its help text (ending in
        one newline).
    """
    if parser is None:
        from sarship.cli import build_parser

        parser = build_parser()
    texts = {}
    for name, p in {"sarship": parser, **{f"sarship {c}": s for c, s in subcommands(parser).items()}}.items():
        _fixed_width(p)
        texts[name] = p.format_help().rstrip() + "\n"
    return texts


def block(command: str, text: str) -> str:
    """The marked Markdown block holding ``command``'s help ``text``."""
    return f"<!-- BEGIN GENERATED: {command} --help -->\n```text\n{text}```\n<!-- END GENERATED -->"


def rewrite(page: str, texts: dict[str, str]) -> str:
    """``page`` with every generated block replaced by the help text of its command.

    Blocks of commands the parser no longer has are removed; commands without a block get a
    new section at the end of the page.

    Parameters
    ----------
    page : str
        The Markdown page (docs/interfaces/cli.md).
    texts : dict of str to str
        :func:`help_texts`.

    Returns
    -------
    str
        The page as it must be committed.
    """
    seen: set[str] = set()

    def replace(m: re.Match) -> str:
        cmd = m.group("cmd")
        seen.add(cmd)
        return block(cmd, texts[cmd]) if cmd in texts else ""

    out = _BLOCK.sub(replace, page)
    missing = [c for c in texts if c not in seen]
    for cmd in missing:
        out = out.rstrip("\n") + f"\n\n## `{cmd}`\n\n{block(cmd, texts[cmd])}\n"
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m sarship.docs_cli [--check] [PAGE]``: rewrite (or check) the page."""
    ap = argparse.ArgumentParser(prog="python -m sarship.docs_cli", description=__doc__.split("\n\n")[0])
    ap.add_argument("page", nargs="?", type=Path, default=PAGE, help=f"the page (default {PAGE})")
    ap.add_argument("--check", action="store_true", help="exit 1 if the page differs from the parser; write nothing")
    a = ap.parse_args(argv)
    try:
        page = a.page.read_text(encoding="utf-8")
    except OSError as exc:
        print(f"{ap.prog}: error: cannot read {a.page}: {exc.strerror}", file=sys.stderr)
        return 2
    want = rewrite(page, help_texts())
    if want == page:
        return 0
    if a.check:
        print(
            f"{a.page} differs from the sarship parser's help: run `{REGENERATE}` in the repository "
            "and commit the page",
            file=sys.stderr,
        )
        return 1
    tmp = a.page.with_name(f".{a.page.name}.partial")
    tmp.write_text(want, encoding="utf-8")
    tmp.replace(a.page)
    print(f"rewrote {a.page}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
