"""The layers import downward only: ``sarship.pipeline`` (pure array code) <- ``sarship.workers``
(cluster, routing, the orchestration of a run) <- ``sarship.service`` (HTTP, store, ingest, web)
<- ``sarship.cli`` (the command line).

Every import statement of every module is parsed (also those inside functions, which is where
the slow imports sit), relative imports resolved, so a late ``from sarship.service import x`` in
a worker module fails here as surely as one at the top.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
#: repository folder -> the package it installs as (pyproject.toml's package-dir)
ROOTS = {
    "pipeline": "sarship.pipeline",
    "workers": "sarship.workers",
    "service": "sarship.service",
    "sarship": "sarship",
}
#: what each layer may import of the project
ALLOWED = {
    "sarship.pipeline": {"sarship.pipeline"},
    "sarship.workers": {"sarship.pipeline", "sarship.workers"},
    "sarship.service": {"sarship.pipeline", "sarship.workers", "sarship.service"},
    "sarship": {"sarship.pipeline", "sarship.workers", "sarship.service", "sarship"},
}
#: the command line's own modules (the console script, ``python -m sarship``, the warm process that
#: runs its commands, the generator of its reference page): the only importers of ``sarship.cli``
COMMAND_LINE = {"sarship.__main__", "sarship.launch", "sarship.warm", "sarship.warm_process", "sarship.docs_cli"}
#: third-party packages a layer must not use: no cluster and no web in the science
FORBIDDEN_THIRD_PARTY = {
    "sarship.pipeline": {"distributed", "dask", "fastapi", "starlette", "uvicorn", "httpx", "prometheus_client"},
    "sarship.workers": {"fastapi", "starlette", "uvicorn", "prometheus_client"},
}


def _modules():
    for folder, package in ROOTS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = path.relative_to(REPO / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts])
            is_pkg = path.name == "__init__.py"
            yield path, name, is_pkg


def _imports(path: Path, name: str, is_pkg: bool) -> list[tuple[int, str]]:
    """``(line, absolute module name)`` of every import in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if is_pkg else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names if a.name != "*"]
    return out


def _layer(module: str) -> str:
    for layer in ("sarship.pipeline", "sarship.workers", "sarship.service"):
        if module == layer or module.startswith(layer + "."):
            return layer
    return "sarship"


def _project(module: str) -> str | None:
    """The project layer ``module`` belongs to, or None for third-party modules."""
    if module == "sarship" or module.startswith("sarship."):
        return _layer(module)
    return None


MODULES = list(_modules())


def test_every_layer_has_modules():
    layers = {_layer(name) for _, name, _ in MODULES}
    assert layers == set(ALLOWED), layers
    assert len(MODULES) > 40


def test_layers_import_downward_only():
    bad = []
    for path, name, is_pkg in MODULES:
        layer = _layer(name)
        for line, mod in _imports(path, name, is_pkg):
            top = mod.split(".")[0]
            where = f"{path.relative_to(REPO)}:{line}"
            if top in ("pipeline", "workers", "service"):
                bad.append(f"{where}: imports '{mod}' by its repository folder, not as sarship.{mod}")
                continue
            target = _project(mod)
            if target is None:
                if top in FORBIDDEN_THIRD_PARTY.get(layer, ()):
                    bad.append(f"{where}: {layer} must not use '{top}'")
                continue
            if target not in ALLOWED[layer]:
                bad.append(f"{where}: {layer} imports {mod} (a layer above it)")
            if mod.startswith("sarship.cli") and name not in COMMAND_LINE:
                bad.append(f"{where}: only the command line's own modules may import it")
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_checker_sees_a_violation(tmp_path):
    """The parser finds an upward import inside a function and resolves relative imports."""
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from ..service import app\n    import sarship.workers.jobs\n")
    found = dict((m, ln) for ln, m in _imports(src, "sarship.pipeline.x", False))
    assert found["sarship.service"] == 2 and found["sarship.service.app"] == 2
    assert "sarship.workers.jobs" in found
    assert _project("sarship.service.app") not in ALLOWED["sarship.pipeline"]


@pytest.mark.parametrize("layer", ["sarship.pipeline", "sarship.workers"])
def test_lower_layers_import_alone(layer):
    """Importing every module of a lower layer loads nothing of the layers above it."""
    import importlib

    names = [n for _, n, _ in MODULES if _layer(n) == layer and ".gpu" not in n]
    code = (
        "import importlib, sys\n"
        f"for n in {names!r}:\n    importlib.import_module(n)\n"
        "print(sorted({m for m in sys.modules if m.startswith('sarship.')}))\n"
    )
    import subprocess

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO.parent, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    loaded = ast.literal_eval(out.stdout.strip().splitlines()[-1])
    above = [m for m in loaded if _layer(m) not in ALLOWED[layer] and m != "sarship"]
    assert not above, f"importing {layer} loaded {above}"
    assert importlib.util.find_spec("sarship") is not None


def _module_graph(modules) -> dict[str, set[str]]:
    """Module -> the project modules it imports (every import statement, also inside functions;
    ``from package import name`` counts as importing ``package.name`` when that is a module)."""
    known = {name: (path, is_pkg) for path, name, is_pkg in modules}
    graph: dict[str, set[str]] = {}
    for name, (path, is_pkg) in known.items():
        deps = set()
        for _, mod in _imports(path, name, is_pkg):
            while mod and mod not in known:
                mod = mod.rpartition(".")[0]
            if mod and mod != name:
                deps.add(mod)
        graph[name] = deps
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected components of more than one module (Tarjan 1972,
    iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on_stack.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_circle():
    """No two modules of the product import each other, directly or through others (issue 32:
    a GPU twin is named on its detector's spec and resolved by name, so the twin may import
    its detector's maths; the warm process gets the command line passed in)."""
    circles = _circles(_module_graph(MODULES))
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_circle_checker_finds_one(tmp_path):
    """The checker finds a circle made by an import inside a function, and none in a chain."""
    (tmp_path / "a.py").write_text("import sarship.pipeline.b\n")
    (tmp_path / "b.py").write_text("def f():\n    from sarship.pipeline import a\n")
    (tmp_path / "c.py").write_text("from sarship.pipeline.b import f\n")
    mods = [(tmp_path / f"{n}.py", f"sarship.pipeline.{n}", False) for n in "abc"]
    g = _module_graph(mods)
    assert g == {
        "sarship.pipeline.a": {"sarship.pipeline.b"},
        "sarship.pipeline.b": {"sarship.pipeline.a"},
        "sarship.pipeline.c": {"sarship.pipeline.b"},
    }
    assert _circles(g) == [["sarship.pipeline.a", "sarship.pipeline.b"]]
    del g["sarship.pipeline.b"]
    assert _circles({**g, "sarship.pipeline.b": set()}) == []


def test_every_gpu_twin_resolves():
    """A detector's ``gpu`` names its twin; every name resolves (the twin modules import CuPy
    only when they run, so this needs no GPU) to a function, or a module with the functions its
    detector calls."""
    from sarship.pipeline import detectors

    with_twin = [n for n in detectors.names() if detectors.get(n).gpu]
    assert len(with_twin) >= 13, with_twin
    for n in with_twin:
        spec = detectors.get(n)
        twin = spec.twin()
        assert spec.gpu.startswith("sarship.pipeline.gpu."), spec.gpu
        if ":" in spec.gpu:
            assert callable(twin), (n, spec.gpu)
        else:
            assert all(callable(getattr(twin, f, None)) for f in ("labels", "detect")), (n, spec.gpu)
    import dataclasses

    with pytest.raises(ValueError, match="no GPU twin"):
        dataclasses.replace(detectors.get("ca_cfar"), gpu=None).twin()
