"""The code is linted, formatted and type-checked by the test command, so CI enforces it.

- ``ruff check`` (pycodestyle, pyflakes, isort, pyupgrade, bugbear) and ``ruff format --check`` over
  the repository, with the configuration of ``pyproject.toml`` (``[tool.ruff]``);
- ``mypy``, strict, on ``sarship.pipeline.run`` (the plan and stages of a run) and
  ``sarship.service`` (``[tool.mypy]``), the modules they import read for their types;
- the links that let editors and type checkers resolve the import root in the checkout
  (``sarship/pipeline`` -> ``pipeline/`` and so on: README, "Editors and type checkers");
- no function of the product over :data:`MAX_FUNCTION_LINES` lines.

Each tool runs as a subprocess from the repository root, as a developer runs it; its own output is
the failure message.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
#: the longest function the product may have (``def`` line to last line, docstring included)
MAX_FUNCTION_LINES = 120
PRODUCT = ("pipeline", "workers", "service", "sarship")


def _tool(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_COLOR": "1"}
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env
    )


def test_ruff_lint():
    r = _tool("ruff", "check", "--no-cache", "--output-format", "concise", ".")
    assert r.returncode == 0, f"ruff check found problems:\n{r.stdout}{r.stderr}"


def test_ruff_format():
    r = _tool("ruff", "format", "--no-cache", "--check", ".")
    assert r.returncode == 0, f"ruff format would change files (run `ruff format .`):\n{r.stdout}{r.stderr}"


def test_mypy_strict_on_the_run_and_the_service(tmp_path):
    r = _tool("mypy", "--cache-dir", str(tmp_path / "mypy-cache"))
    assert r.returncode == 0, f"mypy:\n{r.stdout}{r.stderr}"
    assert "sarship.pipeline.run" in (REPO / "pyproject.toml").read_text()  # what it checked


@pytest.mark.parametrize("folder", ["pipeline", "workers", "service"])
def test_the_import_root_resolves_in_the_checkout(folder):
    link = REPO / "sarship" / folder
    assert link.is_symlink() and os.readlink(link) == f"../{folder}", f"sarship/{folder} must link to ../{folder}"
    assert (link / "__init__.py").resolve() == (REPO / folder / "__init__.py").resolve()


def _functions():
    for folder in PRODUCT:
        for path in sorted((REPO / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    yield path.relative_to(REPO), node


def test_no_function_of_the_product_is_over_the_limit():
    long = [
        f"{path}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for path, node in _functions()
        if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"
    assert sum(1 for _ in _functions()) > 500  # the walk found the product
