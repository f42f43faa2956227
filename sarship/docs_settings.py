"""The table of every ``SARSHIP_*`` environment variable in docs/interfaces/settings.md, generated
from the settings models.

The rows come from :data:`sarship.pipeline.settings.VARIABLES` (the variables the pipeline, the
workers and the command line read, some shared with the service) and from the service's
:class:`sarship.service.settings.Settings` (its own fields); they are rendered into the block of
the page marked ``<!-- BEGIN GENERATED: settings -->`` ... ``<!-- END GENERATED -->``, the prose
around it hand-written. Regenerate after changing a variable::

    python -m sarship.docs_settings            # rewrites docs/interfaces/settings.md in place
    python -m sarship.docs_settings --check    # exit 1 when the page differs from the models

``tests/project/test_settings_vars.py`` runs the check.
"""

from __future__ import annotations

import argparse
import re
import sys
import typing
from pathlib import Path
from typing import Any

#: The page, relative to the repository root (the default of the command line).
PAGE = Path("docs") / "interfaces" / "settings.md"
#: The command that regenerates the page, quoted by the check's message.
REGENERATE = "python -m sarship.docs_settings"
#: Who reads the service's own fields.
SERVICE = "sarship.service (sarship serve)"

_BLOCK = re.compile(r"<!-- BEGIN GENERATED: settings -->\n.*?<!-- END GENERATED -->", re.S)


def type_name(annotation: Any) -> str:
    """A short name of a field's type: ``float``, ``int or none``, ``one of zarr, tensorstore``.

    Parameters
    ----------
    annotation : Any
        A type annotation (a class, ``Optional[...]``, ``Literal[...]``, ``list[...]``).

    Returns
    -------
    str
    """
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin is typing.Union or (origin is not None and getattr(origin, "__name__", "") == "UnionType"):
        parts = [type_name(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or none" if type(None) in args else "")
    if origin is typing.Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if origin is not None:
        return f"{getattr(origin, '__name__', str(origin))} of {', '.join(type_name(a) for a in args)}"
    if annotation is type(None):
        return "none"
    return getattr(annotation, "__name__", str(annotation))


def bounds(field: Any) -> str:
    """A field's bounds as the table shows them: ``> 0, finite`` (empty when it has none).

    Parameters
    ----------
    field : pydantic.fields.FieldInfo

    Returns
    -------
    str
    """
    signs = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
    out = []
    for m in field.metadata:
        for attr, sign in signs.items():
            if getattr(m, attr, None) is not None:
                out.append(f"{sign} {getattr(m, attr):g}")
        if getattr(m, "allow_inf_nan", None) is False:
            out.append("finite")
        if getattr(m, "pattern", None):
            out.append(f"matching {m.pattern}")
    return ", ".join(out)


def _typed(field: Any) -> str:
    """Type and bounds: ``float (> 0, finite)``."""
    b = bounds(field)
    return type_name(field.annotation) + (f" ({b})" if b else "")


def _default(field: Any) -> str:
    """A field's default as the table shows it (the same rule as ``sarship serve --help``)."""
    from pydantic_core import PydanticUndefined

    if field.default_factory is not None:
        return repr(field.default_factory())
    if field.default is PydanticUndefined:
        return "required"
    return "none" if field.default is None else str(field.default)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def rows() -> list[tuple[str, str, str, str, str]]:
    """``(variable, type, default, meaning, read by)`` of every ``SARSHIP_*`` variable, sorted
    by variable.

    Returns
    -------
    list of tuple of str
    """
    from sarship.pipeline import settings
    from sarship.service.settings import Settings

    model = settings.model()
    out = []
    for name, var in settings.VARIABLES.items():
        f = model.model_fields[name]
        out.append((var.env, _typed(f), var.default_text or _default(f), var.meaning, ", ".join(var.readers)))
    for name, f in Settings.model_fields.items():
        if name not in settings.VARIABLES:
            out.append((settings.PREFIX + name.upper(), _typed(f), _default(f), f.description or "", SERVICE))
    return sorted(out)


def table() -> str:
    """The Markdown table of :func:`rows`, ending in one newline.

    Returns
    -------
    str
    """
    lines = ["| Variable | Type | Default | Meaning | Read by |", "|---|---|---|---|---|"]
    lines += ["| " + " | ".join(_cell(c) for c in (f"`{r[0]}`", *r[1:])) + " |" for r in rows()]
    return "\n".join(lines) + "\n"


def rewrite(text: str) -> str:
    """``text`` (the page) with its generated block replaced by :func:`table`.

    Parameters
    ----------
    text : str
        The page; it must hold one generated block.

    Returns
    -------
    str
    """
    if not _BLOCK.search(text):
        raise ValueError("the page has no '<!-- BEGIN GENERATED: settings -->' block")
    block = "<!-- BEGIN GENERATED: settings -->\n" + table() + "<!-- END GENERATED -->"
    return _BLOCK.sub(lambda _: block, text, count=1)


def main(argv: list[str] | None = None) -> int:
    """Rewrite the page, or with ``--check`` exit 1 when it differs from the models."""
    p = argparse.ArgumentParser(prog="python -m sarship.docs_settings", description=__doc__.splitlines()[0])
    p.add_argument("page", nargs="?", default=str(PAGE), help=f"the page (default {PAGE})")
    p.add_argument("--check", action="store_true", help="exit 1 when the page differs from the models")
    a = p.parse_args(argv)
    page = Path(a.page)
    text = page.read_text()
    new = rewrite(text)
    if a.check:
        if new != text:
            print(f"{page} differs from the settings models: run {REGENERATE}", file=sys.stderr)
            return 1
        return 0
    if new != text:
        page.write_text(new)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
