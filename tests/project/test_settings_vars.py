"""Every ``SARSHIP_*`` variable is declared once (``sarship.pipeline.settings``, or the service's
own ``Settings``), read through those definitions at call time, and listed in one generated
table (docs/interfaces/settings.md)."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

from sarship.pipeline import settings
from sarship.pipeline.errors import InputError

REPO = Path(__file__).resolve().parents[2]
PRODUCT = ("pipeline", "workers", "service", "sarship")
#: The one module that reads the environment for them.
READER = REPO / "pipeline" / "settings.py"


def _product_files():
    for folder in PRODUCT:
        yield from sorted((REPO / folder).rglob("*.py"))


def _is_environ(node: ast.AST) -> bool:
    """``os.environ`` or a bare ``environ``."""
    return (isinstance(node, ast.Attribute) and node.attr == "environ") or (
        isinstance(node, ast.Name) and node.id == "environ"
    )


def _variable(node: ast.AST) -> str | None:
    if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("SARSHIP_"):
        return node.value
    return None


def direct_reads(source: str) -> list[tuple[int, str]]:
    """``(line, variable)`` of every read of a ``SARSHIP_*`` variable from the environment:
    ``os.environ.get(V)``, ``os.getenv(V)``, ``os.environ[V]`` (read), ``V in os.environ``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and node.args and (name := _variable(node.args[0])):
            f = node.func
            if (
                isinstance(f, ast.Attribute) and ((f.attr == "get" and _is_environ(f.value)) or f.attr == "getenv")
            ) or (isinstance(f, ast.Name) and f.id == "getenv"):
                out.append((node.lineno, name))
        elif (
            isinstance(node, ast.Subscript)
            and isinstance(node.ctx, ast.Load)
            and _is_environ(node.value)
            and (name := _variable(node.slice))
        ):
            out.append((node.lineno, name))
        elif (
            isinstance(node, ast.Compare)
            and (name := _variable(node.left))
            and any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops)
            and any(map(_is_environ, node.comparators))
        ):
            out.append((node.lineno, name))
    return out


def test_the_checker_sees_every_form():
    src = (
        "import os\nfrom os import environ, getenv\n"
        "a = os.environ.get('SARSHIP_A', '')\nb = os.getenv('SARSHIP_B')\nc = os.environ['SARSHIP_C']\n"
        "d = 'SARSHIP_D' in os.environ\ne = getenv('SARSHIP_E')\n"
        "os.environ['SARSHIP_W'] = '1'\nos.environ.setdefault('SARSHIP_S', '1')\nx = os.environ.get('HOME')\n"
    )
    assert [n for _, n in direct_reads(src)] == ["SARSHIP_A", "SARSHIP_B", "SARSHIP_C", "SARSHIP_D", "SARSHIP_E"]


def test_no_module_reads_a_variable_but_through_the_settings():
    bad = []
    for path in _product_files():
        if path == READER:
            continue
        bad += [
            f"{path.relative_to(REPO)}:{line}: reads {name} from the environment: use sarship.pipeline.settings.read"
            for line, name in direct_reads(path.read_text())
        ]
    assert not bad, "\n".join(bad)


def _known() -> set[str]:
    from sarship.service.settings import Settings

    return {v.env for v in settings.VARIABLES.values()} | {settings.PREFIX + n.upper() for n in Settings.model_fields}


#: Names that are no setting of sarship (docs/interfaces/settings.md says so): the docs' placeholder,
#: the deployment's own build arguments and unit substitutions, the tests' and benchmarks' knobs.
NOT_SETTINGS = {
    "SARSHIP_NAME",
    "SARSHIP_UID",
    "SARSHIP_GID",
    "SARSHIP_CPU_WORKERS",
    "SARSHIP_SCHEDULER_ADDRESS",
    "SARSHIP_DASHBOARD_ADDRESS",
    "SARSHIP_FUZZ_EXAMPLES",
    "SARSHIP_BENCH_TMP",
}


def test_every_variable_named_is_defined():
    """A ``SARSHIP_*`` name in the product's code or docs is a defined variable (no stale name)."""
    names = re.compile(r"\bSARSHIP_[A-Z0-9][A-Z0-9_]*[A-Z0-9]\b")
    files = [
        *_product_files(),
        REPO / "README.md",
        *sorted((REPO / "docs").rglob("*.md")),
        *sorted(p for p in (REPO / "deploy").rglob("*") if p.is_file() and "static" not in p.parts),
        REPO / "docker-compose.yml",
    ]
    unknown = {}
    known = _known() | NOT_SETTINGS
    for path in files:
        for name in set(names.findall(path.read_text())) - known:
            unknown.setdefault(name, []).append(str(path.relative_to(REPO)))
    assert not unknown, unknown


def test_shared_variables_are_defined_once():
    """The service's fields that the layers below read too are the definitions' fields."""
    from sarship.service.settings import Settings

    shared = set(Settings.model_fields) & set(settings.VARIABLES)
    assert shared == {"scheduler", "land_max_mb"}
    model = settings.model()
    for name in shared:
        mine, theirs = Settings.model_fields[name], model.model_fields[name]
        assert (mine.annotation, mine.default, mine.description, mine.metadata) == (
            theirs.annotation,
            theirs.default,
            theirs.description,
            theirs.metadata,
        ), name


def test_the_table_is_the_models():
    from sarship.docs_settings import PAGE, REGENERATE, rewrite

    page = (REPO / PAGE).read_text()
    assert rewrite(page) == page, f"{PAGE} differs from the settings models: run {REGENERATE}"
    for env in _known():
        assert f"| `{env}` |" in page, env


def test_the_table_is_linked():
    for doc in ("README.md", "docs/architecture.md", "docs/README.md"):
        assert "interfaces/settings.md" in (REPO / doc).read_text(), doc


#: (variable, text, value) read at call time; None: the default.
GOOD = [
    ("reader", " ZARR ", "zarr"),
    ("reader", "", None),
    ("ingest_writers", "3", 3),
    ("land_max_mb", "0.5", 0.5),
    ("threads_max_px", "1e3", 1000),
    ("cluster_host", "[::1]", "::1"),
    ("cluster_host", "node-1.local", "node-1.local"),
    ("worker_start", "Spawn", "spawn"),
    ("gpu_procs", "0", 1),
    ("gpu_threads", "4", 4),
    ("block_cache_mb", "0", 0.0),
    ("cuda_warmup", "0", False),
    ("cuda_warmup", "no", True),
    ("fast_exit", "0", False),
    ("debug", " ", True),
    ("debug", "", False),
    ("warm", " Off ", False),
    ("warm", "1", True),
    ("scheduler", " tcp://h:8786 ", "tcp://h:8786"),
    ("scheduler", "  ", None),
    ("warm_socket", "/tmp/w.sock", Path("/tmp/w.sock")),
    ("gpu_hsum", "direct", "direct"),
    ("gpu_pool_fraction", "0.5", 0.5),
]
#: (variable, text, message) of a bad value: the messages the tests of each reader assert.
BAD = [
    ("reader", "Foo", "SARSHIP_READER must be one of tensorstore, zarr, got 'foo'"),
    ("ingest_writers", "0", "SARSHIP_INGEST_WRITERS must be a whole number >= 1, got '0'"),
    ("land_max_mb", "inf", "SARSHIP_LAND_MAX_MB must be a positive number of MiB, got 'inf'"),
    ("threads_max_px", "-1", "SARSHIP_THREADS_MAX_PX must be a whole number of pixels >= 0, got '-1'"),
    ("cluster_host", "a b", "SARSHIP_CLUSTER_HOST must be an IP address or host name of this machine, got 'a b'"),
    ("worker_start", "thread", "SARSHIP_WORKER_START must be one of fork, forkserver, spawn, got 'thread'"),
    ("gpu_procs", "", "SARSHIP_GPU_PROCS must be a whole number, got ''"),
    ("gpu_threads", "x", "SARSHIP_GPU_THREADS must be a whole number, got 'x'"),
    ("block_cache_mb", "nan", "SARSHIP_BLOCK_CACHE_MB must be a number of MiB >= 0, got 'nan'"),
    ("gpu_hsum", "fast", "SARSHIP_GPU_HSUM must be one of direct, transpose, got 'fast'"),
    ("gpu_pool_fraction", "most", "SARSHIP_GPU_POOL_FRACTION must be a number, got 'most'"),
]


@pytest.mark.parametrize("name,text,value", GOOD)
def test_read_at_call_time(monkeypatch, name, text, value):
    var = settings.VARIABLES[name]
    monkeypatch.delenv(var.env, raising=False)
    assert settings.read(name) == var.default
    monkeypatch.setenv(var.env, text)
    want = var.default if value is None else value
    assert settings.read(name) == want
    if not var.typed_by_model:  # the model gives what read gives
        assert getattr(settings.model()(), name) == want


@pytest.mark.parametrize("name,text,message", BAD)
def test_a_bad_value_is_one_line(monkeypatch, name, text, message):
    monkeypatch.setenv(settings.VARIABLES[name].env, text)
    with pytest.raises(InputError) as exc:
        settings.read(name)
    assert str(exc.value) == message
    if not settings.VARIABLES[name].typed_by_model:
        with pytest.raises(ValueError, match=re.escape(message)):
            settings.model()()


def test_the_readers_take_their_values_from_it(monkeypatch):
    from sarship.pipeline.land.landmask_files import land_max_bytes
    from sarship.pipeline.readers.writing import ingest_writers
    from sarship.pipeline.tiling.inputs import reader_backend
    from sarship.workers import blockcache, cluster

    for env, text in (
        ("SARSHIP_READER", "zarr"),
        ("SARSHIP_LAND_MAX_MB", "2"),
        ("SARSHIP_INGEST_WRITERS", "5"),
        ("SARSHIP_BLOCK_CACHE_MB", "1"),
        ("SARSHIP_THREADS_MAX_PX", "7"),
        ("SARSHIP_WORKER_START", "forkserver"),
        ("SARSHIP_GPU_PROCS", "3"),
    ):
        monkeypatch.setenv(env, text)
    assert (reader_backend(), land_max_bytes(), ingest_writers(), blockcache.limit_bytes()) == (
        "zarr",
        2 * 2**20,
        5,
        2**20,
    )
    assert (cluster.threads_max_px(), cluster.worker_start_method(), cluster.gpu_procs(2)) == (7, "forkserver", 3)


def test_reading_imports_only_the_standard_library():
    """The command's end of the warm cluster reads its variables before anything heavy loads."""
    code = (
        "import sys\nfrom sarship.pipeline import settings\n"
        "[settings.read(n) for n in settings.VARIABLES]\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pydantic', 'pydantic_settings', 'numpy')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        env={"PATH": "/usr/bin:/bin", "SARSHIP_WARM": "0", "SARSHIP_READER": "zarr"},
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
