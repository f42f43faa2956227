"""The installed product has one import root, ``sarship``, in a fresh virtualenv.

The wheel is built from the working tree (pip, the project's own build backend) and installed
with pip into a new virtualenv that borrows this interpreter's third-party packages (a ``.pth``
path file, so nothing is downloaded and this environment's own ``sarship`` is not visible).
From a folder outside the repository it then checks what a user gets: ``import sarship.pipeline``
works, ``import pipeline`` / ``workers`` / ``service`` do not, every module imports, the console
script and ``python -m sarship`` answer, and site-packages holds nothing generic.

The README's order (``pip install .``, a job, then ``pip install -e '.[test]'`` for the tests) is
run in one fresh virtualenv: the job must leave no Numba cache in site-packages (``*.nbi`` /
``*.nbc`` files survive ``pip uninstall`` and the ``site-packages/sarship/`` folder they keep
shadowed the editable install: issue 30), and the editable install must then work.
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _run(cmd, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)


def _copy_source(dest: Path) -> Path:
    """A clean copy of what the build reads (no stale build/ folder, no caches of the repository)."""
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, dest / name)
    for folder in ("pipeline", "workers", "service", "sarship"):
        shutil.copytree(REPO / folder, dest / folder, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    return dest


def _new_venv(root: Path) -> tuple[Path, Path]:
    """A new virtualenv at ``root`` borrowing this interpreter's third-party packages (a ``.pth``
    path file: nothing is downloaded; paths named in a ``.pth`` are not scanned for ``.pth``
    files, so this environment's own editable sarship stays invisible). Returns its Python and
    its site-packages."""
    venv.EnvBuilder(with_pip=False).create(root)
    py = root / "bin" / "python"
    purelib = Path(_run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    ours = {
        sysconfig.get_paths()["purelib"],
        sysconfig.get_paths()["platlib"],
        *site.getsitepackages(),
        *(p for p in sys.path if Path(p).name == "site-packages"),
    }  # and those this one borrows
    (purelib / "_borrowed_deps.pth").write_text("\n".join(sorted(ours)) + "\n")
    return py, purelib


def _user_env(home: Path) -> dict[str, str]:
    """A user's environment: their own home and cache folder, no Numba cache setting, no
    PYTHONPATH, no GPU."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH", "XDG_CACHE_HOME")}
    home.mkdir(parents=True, exist_ok=True)
    return {**env, "HOME": str(home), "CUDA_VISIBLE_DEVICES": ""}


def _numba_files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for pat in ("*.nbi", "*.nbc") for p in folder.rglob(pat))


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    src = _copy_source(tmp_path_factory.mktemp("src"))
    r = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", out, src])
    if r.returncode != 0:
        pytest.fail(f"pip wheel failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}")
    (whl,) = out.glob("sarship-*.whl")
    return whl


@pytest.fixture(scope="module")
def fresh_env(wheel, tmp_path_factory) -> Path:
    """A new virtualenv with the wheel installed by pip, its dependencies borrowed."""
    root = tmp_path_factory.mktemp("venv")
    py, _ = _new_venv(root)
    r = _run([py, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--prefix", root, wheel])
    if r.returncode != 0:
        pytest.fail(f"pip install of the wheel failed:\n{r.stderr[-3000:]}")
    return root


def test_wheel_has_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"sarship"}, sorted(tops)
    files = set(names)
    for folder, pkg in (
        ("pipeline", "sarship/pipeline"),
        ("workers", "sarship/workers"),
        ("service", "sarship/service"),
        ("sarship", "sarship"),
    ):
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


def _readme_order(wheel: Path, tmp_path: Path, job: list[list[str]]) -> tuple[Path, Path, dict[str, str]]:
    """The README's order in one fresh virtualenv, up to the editable install: ``pip install .``
    (the wheel, not editable), the ``job`` commands (run in ``tmp_path/work``), then
    ``pip install -e`` of a copy of the source as ``pip install -e '.[test]'`` does (its build
    isolated, as the wheel's; no deps: they are borrowed). Returns the virtualenv, its site-packages and the user's environment."""
    root = tmp_path / "venv"
    py, purelib = _new_venv(root)
    env = _user_env(tmp_path / "home")
    r = _run([py, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--prefix", root, wheel], env=env)
    assert r.returncode == 0, f"pip install of the wheel failed:\n{r.stderr[-3000:]}"
    work = tmp_path / "work"
    work.mkdir()
    for cmd in job:
        r = _run([root / "bin" / cmd[0], *cmd[1:]], cwd=work, env=env)
        assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stderr[-3000:]}"
    assert _numba_files(purelib) == [], "Numba wrote its cache into site-packages"
    assert _numba_files(tmp_path / "home" / ".cache" / "sarship" / "numba"), "no Numba cache in the user's cache folder"
    src = _copy_source(tmp_path / "checkout")
    r = _run([py, "-m", "pip", "install", "--no-deps", "-q", "--prefix", root, "-e", src], env=env)
    assert r.returncode == 0, f"pip install -e failed:\n{r.stderr[-3000:]}"
    left = sorted(str(p.relative_to(purelib)) for p in (purelib / "sarship").rglob("*"))
    assert left == [], f"the non-editable install left {left[:5]} in site-packages (they shadow the editable one)"
    r = _run([root / "bin" / "sarship", "detectors", "--json"], cwd=work, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert {d["name"] for d in json.loads(r.stdout)} >= {"ca_cfar", "os_cfar", "k_cfar"}
    r = _run(
        [py, "-c", "import sarship.pipeline.detectors.base, sarship.cli; print(sarship.pipeline.__file__)"],
        cwd=work,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().startswith(str(src)), r.stdout  # the editable checkout, nothing else
    return root, purelib, env


def test_readme_install_order_keeps_numba_caches_out_of_site_packages(wheel, tmp_path):
    """``pip install .``, one of sarship's cached Numba kernels compiled (the cheapest job that
    writes a cache file), then ``pip install -e``: site-packages keeps nothing of sarship's and
    the editable install imports every detector. The same with a real simulate + detect before
    and after: the slow sibling below."""
    code = "import numpy as np; from sarship.pipeline.targets.components import mask_points; mask_points(np.eye(3, dtype=bool))"
    _readme_order(wheel, tmp_path, [["python", "-c", code]])


@pytest.mark.slow
def test_readme_install_order_with_a_detect_before_and_after(wheel, tmp_path):
    """The README's three commands in order, with a small job: simulate + detect (land mask and
    ca_cfar kernels compiled and cached) on the installed wheel, then the editable install, then
    a detect again on it."""
    job = [
        ["sarship", "simulate", "s.zarr", "--shape", "256x256", "--ships", "2", "--tile", "256"],
        ["sarship", "detect", "s.zarr", "--detector", "ca_cfar", "--out", "run1", "--scheduler", "local"],
    ]
    root, _, env = _readme_order(wheel, tmp_path, job)
    r = _run(
        [
            root / "bin" / "sarship",
            "detect",
            "s.zarr",
            "--detector",
            "ca_cfar",
            "--out",
            "run2",
            "--scheduler",
            "local",
        ],
        cwd=tmp_path / "work",
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    run = json.loads((tmp_path / "work" / "run2" / "run.json").read_text())
    assert run["detector"] == "ca_cfar"


def test_numba_cache_dir_is_the_first_writable_user_cache_folder(tmp_path):
    from sarship import numba_cache_dir

    xdg, home = tmp_path / "xdg", tmp_path / "home"
    assert numba_cache_dir({"XDG_CACHE_HOME": str(xdg), "HOME": str(home)}) == xdg / "sarship" / "numba"
    assert (xdg / "sarship" / "numba").is_dir()
    blocked = tmp_path / "a-file"
    blocked.write_text("")  # XDG_CACHE_HOME naming a file: no folder can be made under it
    assert numba_cache_dir({"XDG_CACHE_HOME": str(blocked), "HOME": str(home)}) == home / ".cache" / "sarship" / "numba"
    got = numba_cache_dir({})
    assert got.parent.name.startswith("sarship-") and got.name == "numba" and site.getsitepackages()[0] not in str(got)


@pytest.mark.parametrize("numba_first", [False, True], ids=["sarship-first", "numba-first"])
def test_sarship_processes_cache_numba_in_the_user_folder(tmp_path, numba_first):
    """Importing sarship sets NUMBA_CACHE_DIR (and Numba's configuration, if Numba was imported
    first); a value the user set wins."""
    code = (
        "import numba; " if numba_first else ""
    ) + "import sarship, os, numba.core.config as c; print(os.environ['NUMBA_CACHE_DIR']); print(c.CACHE_DIR)"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    r = _run([sys.executable, "-c", code], cwd=tmp_path, env={**env, "XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == [str(tmp_path / "xdg" / "sarship" / "numba")] * 2
    r = _run([sys.executable, "-c", code], cwd=tmp_path, env={**env, "NUMBA_CACHE_DIR": str(tmp_path / "mine")})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == [str(tmp_path / "mine")] * 2
