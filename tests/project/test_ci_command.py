"""``.ci/run`` runs exactly the README's test command (the one that installs and runs the tests)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```sh\n(.*?)```", readme, flags=re.S)
    tests = [ln.strip() for b in blocks for ln in b.splitlines() if "pytest" in ln and "pip install" in ln]
    assert len(tests) == 1, tests  # one install-and-test command
    ci = [
        ln.strip()
        for ln in (ROOT / ".ci" / "run").read_text().splitlines()
        if ln.strip() and not ln.startswith(("#", "set ", "cd "))
    ]
    assert ci == tests, (ci, tests)
    assert '-m "not slow"' in tests[0]  # the slow tests are the only ones left out
