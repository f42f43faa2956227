"""The installed product has one import root, ``sarship``, in a fresh virtualenv.

The wheel is built from the working tree (pip, the project's own build backend) and installed
with pip into a new virtualenv that borrows this interpreter's third-party packages (a ``.pth``
path file, so nothing is downloaded and this environment's own ``sarship`` is not visible).
From a folder outside the repository it then checks what a user gets: ``import sarship.pipeline``
works, ``import pipeline`` / ``workers`` / ``service`` do not, every module imports, the console
script and ``python -m sarship`` answer, and site-packages holds nothing generic.
"""

from __future__ import annotations

import json
import shutil
import site
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    src = tmp_path_factory.mktemp("src")  # a clean copy: no stale build/ folder of the repository
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    for folder in ("pipeline", "workers", "service", "sarship"):
        shutil.copytree(REPO / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", out, src])
    if r.returncode != 0:
        pytest.fail(f"pip wheel failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}")
    (whl,) = out.glob("sarship-*.whl")
    return whl


@pytest.fixture(scope="module")
def fresh_env(wheel, tmp_path_factory) -> Path:
    """A new virtualenv with the wheel installed by pip, its dependencies borrowed."""
    root = tmp_path_factory.mktemp("venv")
    venv.EnvBuilder(with_pip=False).create(root)
    py = root / "bin" / "python"
    purelib = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()}
    (purelib / "_borrowed_deps.pth").write_text("\n".join(sorted(ours)) + "\n")
    r = _run([py, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--prefix", root, wheel])
    if r.returncode != 0:
        pytest.fail(f"pip install of the wheel failed:\n{r.stderr[-3000:]}")
    return root


def test_wheel_has_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"sarship"}, sorted(tops)
    files = set(names)
    for folder, pkg in (("pipeline", "sarship/pipeline"), ("workers", "sarship/workers"),
                        ("service", "sarship/service"), ("sarship", "sarship")):
        for path in (REPO / folder).rglob("*.py"):
            rel = path.relative_to(REPO / folder).as_posix()
            assert f"{pkg}/{rel}" in files, f"{folder}/{rel} is not installed (add its package to pyproject.toml)"
    assert "sarship/service/static/index.html" in files  # the web page travels as package data
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "sarship = sarship.launch:console" in zipfile.ZipFile(wheel).read(entry).decode()


def test_fresh_virtualenv_imports_sarship_only(fresh_env, tmp_path):
    py = fresh_env / "bin" / "python"
    code = r"""
import importlib, importlib.util, json, pkgutil, sys, sysconfig, os
import sarship, sarship.pipeline, sarship.workers, sarship.service, sarship.cli
failed = {}
for m in pkgutil.walk_packages(sarship.__path__, "sarship."):
    if ".gpu" in m.name:      # CuPy is an optional extra
        continue
    try:
        importlib.import_module(m.name)
    except Exception as exc:
        failed[m.name] = repr(exc)
site = sysconfig.get_paths()["purelib"]
print(json.dumps({
    "generic": {n: importlib.util.find_spec(n) is not None for n in ("pipeline", "workers", "service")},
    "file": sarship.pipeline.__file__,
    "failed": failed,
    "top": sorted(p for p in os.listdir(site) if not p.startswith(("_", "sarship"))),
}))
"""
    r = _run([py, "-c", code], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert got["generic"] == {"pipeline": False, "workers": False, "service": False}
    assert str(fresh_env) in got["file"], got["file"]  # the installed copy, not the repository
    assert not got["failed"], got["failed"]
    assert got["top"] == [], got["top"]  # nothing but sarship (and pip's own files) was installed


def test_fresh_virtualenv_command_line(fresh_env, tmp_path):
    r = _run([fresh_env / "bin" / "sarship", "--version"], cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("sarship "), r.stderr
    r = _run([fresh_env / "bin" / "python", "-m", "sarship", "detectors", "--json"], cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert {d["name"] for d in json.loads(r.stdout)} >= {"ca_cfar", "os_cfar", "two_parameter", "apwf"}
