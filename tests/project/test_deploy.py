"""The deployment files (docker-compose.yml, deploy/) against the code they start.

Every ``sarship`` command line in the compose file and the systemd units parses with the
real CLI parser (a renamed flag breaks this test, not a deployment), the compose topology is
consistent (shared data volume, scheduler address, health checks), and the same topology
runs for real as processes: ``dask scheduler`` + ``sarship worker --gpus none`` +
``sarship serve --scheduler`` running a job end to end. The images are built (``slow``) only
where a Docker engine answers; what can be checked without one is checked by parsing: the
extras they install, one user for both, the volumes it owns, hadolint's rules. The API's
binds (no tokens on an address other machines reach: refused) and the Dask dashboard (offered
only where it serves, with and without bokeh) run for real."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")
httpx = pytest.importorskip("httpx")
from conftest import REPO, blobs_scene, write_scene  # noqa: E402
from svc import Server, check_problem, free_port, wait_job  # noqa: E402

COMPOSE = REPO / "docker-compose.yml"
DEPLOY = REPO / "deploy"


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _sarship_argv(svc: dict) -> list[str] | None:
    """The ``sarship`` arguments of a compose service (None when it runs something else)."""
    entry = svc.get("entrypoint", ["sarship"])
    if not str(svc.get("image", "")).startswith("sarship") or entry != ["sarship"]:
        return None
    return [os.path.expandvars(str(a)).replace("${SARSHIP_CPU_WORKERS:-2}", "2") for a in svc["command"]]


def test_compose_commands_parse_with_the_cli():
    from sarship.cli import build_parser

    services = _compose()["services"]
    for name, svc in services.items():
        argv = _sarship_argv(svc)
        if argv is None:
            continue
        build_parser().parse_args(argv)  # SystemExit (a test error) on an unknown flag
        if argv[0] in ("worker", "serve"):
            assert "tcp://scheduler:8786" in argv, (name, argv)
    assert {"worker", "serve"} <= {(_sarship_argv(s) or ["-"])[0] for s in services.values()}
    assert services["scheduler"]["entrypoint"] == ["dask", "scheduler"]
    assert "8786" in services["scheduler"]["command"]


def test_compose_shares_one_data_volume_and_builds_existing_dockerfiles():
    doc = _compose()
    for name, svc in doc["services"].items():
        if name == "prometheus":
            continue
        vols = svc.get("volumes") or doc["x-sarship"]["volumes"]
        assert "data:/data" in vols, (name, vols)
        build = svc.get("build") or doc["x-sarship"]["build"]
        assert (REPO / build["dockerfile"]).is_file(), build
    assert "data" in doc["volumes"]
    prom = yaml.safe_load((DEPLOY / "prometheus.yml").read_text())
    targets = {t for sc in prom["scrape_configs"] for c in sc["static_configs"] for t in c["targets"]}
    assert "api:8080" in targets
    for df in ("Dockerfile", "Dockerfile.gpu"):
        text = (DEPLOY / df).read_text()
        for path in ("pipeline", "workers", "service", "pyproject.toml"):
            assert path in text and (REPO / path).exists()


def test_systemd_units_parse_with_the_cli():
    from sarship.cli import build_parser

    env = {}
    for line in (DEPLOY / "systemd" / "sarship.env").read_text().splitlines():
        if line and not line.startswith("#"):
            k, v = line.split("=", 1)
            env[k] = v
    n = 0
    for unit in sorted((DEPLOY / "systemd").glob("*.service")):
        text = unit.read_text()
        assert "[Service]" in text and "[Install]" in text, unit
        exec_line = next(ln for ln in text.splitlines() if ln.startswith("ExecStart="))
        argv = shlex.split(exec_line[len("ExecStart=") :])
        for k, v in env.items():
            argv = [a.replace("${" + k + "}", v) for a in argv]
        assert not any("${" in a for a in argv), (unit.name, argv)
        if argv[0].endswith("/sarship"):
            build_parser().parse_args(argv[1:])
            n += 1
    assert n == 2


def _wait_listening(port: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    import socket

    t_end = time.time() + timeout
    while time.time() < t_end:
        assert proc.poll() is None, "the dask scheduler exited"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    pytest.fail(f"nothing listens on port {port} after {timeout:g} s")


def test_compose_topology_as_processes(tmp_path):
    """``dask scheduler``, ``sarship worker --gpus none --cpus 1`` and ``sarship serve
    --scheduler``: the compose services, run as local processes. A job runs on the external
    worker (not on a cluster of the API's own) and its results are served."""
    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    data = tmp_path / "data"
    write_scene(
        data / "scenes" / "s1.zarr", {"intensity": blobs_scene((260, 240), looks=2.0, seed=4)}, tile=128, looks=2.0
    )
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--dashboard-address",
                ":0",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
    ]
    srv = None
    try:
        _wait_listening(port, procs[0])  # `sarship worker` refuses an address where nothing listens yet
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "sarship",
                    "worker",
                    "--scheduler",
                    addr,
                    "--gpus",
                    "none",
                    "--cpus",
                    "1",
                    "--name",
                    "box",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                env=env,
            )
        )
        srv = Server(data, free_port(), SARSHIP_SCHEDULER=addr).start()
        r = httpx.post(
            srv.url + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "pfa": 1e-4, "min_area_px": 1}}
        )
        assert r.status_code == 201, r.text
        st = wait_job(srv.url, r.json()["jobID"])
        assert st["status"] == "successful", st
        met = httpx.get(f"{srv.url}/jobs/{st['jobID']}/results/metrics").json()
        assert {t["worker"] for t in met["tiles"]["per_tile"]} == {"box-cpu0"}
        assert httpx.get(srv.url + "/readyz").json()["checks"]["workers"] == 1
        assert json.loads(httpx.get(f"{srv.url}/jobs/{st['jobID']}/results/detections").text)["features"]
    finally:
        if srv is not None:
            srv.stop()
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_compose_api_environment_is_valid_settings(tmp_path, monkeypatch):
    """The API container's SARSHIP_* environment (with compose's ``${VAR:-default}`` defaults)
    validates as service settings; the inbox folder is the container's mount point, made here."""
    from sarship.service.settings import Settings

    env = _compose()["services"]["api"]["environment"]
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for k in [k for k in os.environ if k.startswith("SARSHIP_")]:
        monkeypatch.delenv(k)
    for k, v in env.items():
        v = re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", str(v))
        v = re.sub(r"\$\{SARSHIP_TOKENS:\?[^}]*\}", '["from-dot-env"]', v)  # required: .env gives it
        monkeypatch.setenv(k, str(inbox) if v == "/inbox" else v)
    s = Settings()
    assert s.inbox == [inbox] and [d["detector"] for d in s.inbox_detectors] == ["os_cfar"]
    assert s.concurrency == 2 and s.tokens == ["from-dot-env"]
    assert s.dashboard_url == "http://localhost:8787/status"
    mounts = _compose()["services"]["api"]["volumes"]
    assert any(m.endswith(":/inbox") for m in mounts)


# ----------------------------------------------------------------------------- images (by parsing)

#: the extras real passes need in both images: Sentinel-1 SAFE ingest (the inbox), GeoPackage/KML
#: export, the coastline land mask, and the Dask dashboard
FEATURE_EXTRAS = {"safe", "gis", "coastline", "dashboard"}
IMAGES = {"Dockerfile": FEATURE_EXTRAS, "Dockerfile.gpu": FEATURE_EXTRAS | {"gpu"}}
#: the optional modules those features import, the distribution that brings each and its extra
FEATURE_MODULES = {
    "xarray_sentinel": ("xarray-sentinel", "safe"),
    "pyogrio": ("pyogrio", "gis"),
    "roaring_landmask": ("roaring-landmask", "coastline"),
    "bokeh": ("bokeh", "dashboard"),
}


def _pyproject() -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def _instructions(dockerfile: str) -> list[tuple[str, str]]:
    """The (INSTRUCTION, arguments) of ``deploy/DOCKERFILE``: comments dropped, continued lines joined."""
    out, cur = [], ""
    for line in (DEPLOY / dockerfile).read_text().splitlines():
        if not cur and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            cur += line.rstrip()[:-1] + " "
            continue
        word, _, rest = (cur + line).strip().partition(" ")
        out.append((word.upper(), " ".join(rest.split())))
        cur = ""
    return out


def _run_text(dockerfile: str) -> str:
    return " && ".join(a for i, a in _instructions(dockerfile) if i == "RUN")


def _installed_extras(dockerfile: str) -> set[str]:
    found = re.findall(r"pip install '\.\[([^\]]*)\]'", _run_text(dockerfile))
    assert len(found) == 1, (dockerfile, found)
    return {e.strip() for e in found[0].split(",")}


def test_images_install_the_extras_real_passes_need():
    """Both images install the extras of the inbox's SAFE ingest, the GPKG/KML export, the
    coastline mask and the dashboard (and the GPU one CuPy); every extra exists in pyproject
    (pip only warns about an unknown one); the modules those features import come with those
    extras, and the test extra installs them too, so that CI tests what the images ship."""
    from packaging.requirements import Requirement

    extras = _pyproject()["project"]["optional-dependencies"]
    for dockerfile, need in IMAGES.items():
        got = _installed_extras(dockerfile)
        assert need <= got, (dockerfile, need - got)
        assert got <= set(extras), (dockerfile, got - set(extras))
    code = "\n".join(p.read_text() for d in ("pipeline", "workers", "service") for p in (REPO / d).rglob("*.py"))
    tested = {Requirement(r).name for r in extras["test"]}
    for module, (dist, extra) in FEATURE_MODULES.items():
        assert dist in {Requirement(r).name for r in extras[extra]}, (module, extra, extras[extra])
        assert dist in tested, (dist, "missing from the test extra")
        if module != "bokeh":  # bokeh is imported by distributed's dashboard, not by our code
            assert re.search(rf"^\s*(import|from) {module}\b", code, re.M), f"nothing imports {module} any more"


def test_images_run_as_one_user_that_owns_the_compose_volumes():
    """One non-root uid/gid for both images (build arguments with the same defaults, the same
    that Compose passes), the USER of both; every compose volume is a named volume (the engine
    creates a missing host folder root-owned) mounted where the images made a folder owned by
    that user (a new named volume takes the owner of its mount point), and no service
    overrides the user."""
    doc = _compose()
    ids, owned = {}, {}
    for dockerfile in IMAGES:
        ins = _instructions(dockerfile)
        args = dict(a.split("=", 1) for i, a in ins if i == "ARG")
        ids[dockerfile] = (args["SARSHIP_UID"], args["SARSHIP_GID"])
        assert int(args["SARSHIP_UID"]) > 0 and int(args["SARSHIP_GID"]) > 0, args
        assert [a for i, a in ins if i == "USER"][-1] == "$SARSHIP_UID:$SARSHIP_GID", dockerfile
        run = _run_text(dockerfile)
        assert '--uid "$SARSHIP_UID" --gid "$SARSHIP_GID" sarship' in run, dockerfile
        made = set(re.search(r"mkdir -p ((?:/\S+ ?)+)", run).group(1).split())
        chowned = set(re.search(r'chown "\$SARSHIP_UID:\$SARSHIP_GID" ((?:/\S+ ?)+)', run).group(1).split())
        owned[dockerfile] = made & chowned
    assert len(set(ids.values())) == 1, ids
    builds = {"worker": doc["x-sarship"]["build"], "gpu-worker": doc["services"]["gpu-worker"]["build"]}
    assert builds["worker"]["args"] == builds["gpu-worker"]["args"], builds
    defaults = {k: re.fullmatch(r"\$\{\w+:-(\d+)\}", v).group(1) for k, v in builds["worker"]["args"].items()}
    assert (defaults["SARSHIP_UID"], defaults["SARSHIP_GID"]) == ids["Dockerfile"]
    for name, svc in doc["services"].items():
        if not str(svc.get("image", "sarship")).startswith("sarship"):
            continue
        assert "user" not in svc, name
        dockerfile = (svc.get("build") or doc["x-sarship"]["build"])["dockerfile"].rsplit("/", 1)[-1]
        for mount in svc.get("volumes") or doc["x-sarship"]["volumes"]:
            source, target = str(mount).split(":")[:2]
            assert source in doc["volumes"], (name, mount, "a host folder: created root-owned")
            assert target in owned[dockerfile], (name, mount, owned[dockerfile])
    api = doc["services"]["api"]
    assert f"inbox:{api['environment']['SARSHIP_INBOX']}" in api["volumes"]


def test_dockerfiles_pass_the_lint_rules():
    """What hadolint would flag, by parsing (no hadolint here): a pinned base image (DL3006/7),
    absolute WORKDIRs (DL3000), no ``cd`` (DL3003) or ``sudo`` (DL3004), apt-get with ``-y
    --no-install-recommends`` and its lists removed (DL3014/15, DL3009), pip without its cache
    (DL3042), exec-form ENTRYPOINT/CMD (DL3025: signals reach sarship), a non-root last USER
    (DL3002), ``pipefail`` before a RUN with a pipe (DL4006: a failing ``getent`` would go
    unseen); and every COPY source exists, covering the package folders and the readme.
    (hadolint 2.15 itself passes both files, with the DL3008/DL3013 ignores they explain.)"""
    pyproject = _pyproject()
    package = set(pyproject["tool"]["setuptools"]["package-dir"].values()) | {
        "pyproject.toml",
        pyproject["project"]["readme"],
    }
    for dockerfile in IMAGES:
        ins = _instructions(dockerfile)
        base = [a for i, a in ins if i == "FROM"]
        assert len(base) == 1 and ":" in base[0] and not base[0].endswith(":latest"), base
        copied, pipefail = set(), False
        for i, a in ins:
            if i == "SHELL":
                pipefail = "pipefail" in json.loads(a)
            elif i == "WORKDIR":
                assert a.startswith("/"), (dockerfile, a)
            elif i in ("ENTRYPOINT", "CMD"):
                assert isinstance(json.loads(a), list), (dockerfile, i, a)
            elif i == "COPY":
                sources = a.split()[:-1]
                assert all((REPO / s).exists() for s in sources), (dockerfile, a)
                copied |= set(sources)
            elif i == "RUN":
                words = a.split()
                assert "sudo" not in words and "cd" not in words, (dockerfile, a)
                assert pipefail or "|" not in a.replace("||", ""), (dockerfile, "a pipe without pipefail", a)
                if "apt-get" in words and "install" in words:
                    assert "-y" in words and "--no-install-recommends" in words, a
                    assert "rm -rf /var/lib/apt/lists/*" in a, a
        assert package <= copied, (dockerfile, package - copied)
        assert "PIP_NO_CACHE_DIR=1" in " ".join(a for i, a in ins if i == "ENV"), dockerfile
        assert [a for i, a in ins if i == "USER"][-1].split(":")[0] not in ("root", "0"), dockerfile


def _engine() -> str | None:
    """Why no image can be built here, or None when a Docker engine answers."""
    import shutil

    if not shutil.which("docker"):
        return "no docker client"
    try:
        r = subprocess.run(
            ["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True, timeout=30
        )
    except subprocess.TimeoutExpired:
        return "docker info did not answer in 30 s"
    if r.returncode != 0:
        return f"no Docker engine answers ({(r.stderr.strip().splitlines() or ['docker info failed'])[-1]})"
    return None


@pytest.mark.slow
@pytest.mark.parametrize("dockerfile", sorted(IMAGES))
def test_image_builds_with_its_extras_and_user(dockerfile):
    """Where a Docker engine answers: the image builds, its Python imports every feature
    module, it runs as uid/gid 1000 with /data and /inbox writable, and the CPU image's
    ``serve`` (every interface, no tokens) refuses to start with one line."""
    why = _engine()
    if why:
        pytest.skip(why)
    tag = f"sarship-test-{dockerfile.lower().replace('.', '-')}:{os.getpid()}"
    built = subprocess.run(
        ["docker", "build", "-f", str(DEPLOY / dockerfile), "-t", tag, str(REPO)],
        capture_output=True,
        text=True,
        timeout=3600,
    )
    assert built.returncode == 0, built.stderr[-4000:]
    try:
        probe = (
            f"import os, {', '.join(FEATURE_MODULES)}; "
            "print(os.getuid(), os.getgid(), os.access('/data', os.W_OK), os.access('/inbox', os.W_OK))"
        )
        r = subprocess.run(
            ["docker", "run", "--rm", "--entrypoint", "python", tag, "-c", probe],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert r.stdout.split() == ["1000", "1000", "True", "True"], (r.stdout, r.stderr[-2000:])
        if dockerfile == "Dockerfile":
            r = subprocess.run(["docker", "run", "--rm", tag, "serve"], capture_output=True, text=True, timeout=600)
            lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
            assert r.returncode == 2 and len(lines) == 1 and "SARSHIP_TOKENS" in lines[0], r.stderr
    finally:
        subprocess.run(["docker", "rmi", "-f", tag], capture_output=True, timeout=300)


# ----------------------------------------------------------------------------- binds of the API


def _settings(monkeypatch, **env):
    from sarship.service.settings import Settings

    for k in [k for k in os.environ if k.startswith("SARSHIP_")]:
        monkeypatch.delenv(k)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    return Settings()


@pytest.mark.parametrize(
    "host,env,exposed",
    [
        ("0.0.0.0", {}, True),
        ("::", {}, True),
        ("127.0.0.1", {}, False),
        ("::1", {}, False),
        ("localhost", {}, False),
        ("0.0.0.0", {"SARSHIP_TOKENS": '["t"]'}, False),
        ("0.0.0.0", {"SARSHIP_ALLOW_UNAUTHENTICATED": "1"}, False),
        ("::", {"SARSHIP_ALLOW_UNAUTHENTICATED": "true"}, False),
    ],
)
def test_exposed_address_without_tokens_is_refused(monkeypatch, host, env, exposed):
    from sarship.pipeline.errors import InputError
    from sarship.service.preflight import check_exposure

    settings = _settings(monkeypatch, SARSHIP_HOST=host, **env)
    if exposed:
        with pytest.raises(InputError, match="SARSHIP_TOKENS"):
            check_exposure(settings)
    else:
        check_exposure(settings)


def test_serve_on_every_interface_without_tokens_exits_2(tmp_path):
    """``sarship serve --host 0.0.0.0`` without tokens: exit 2, one line, nothing made; with
    ``--allow-unauthenticated`` that check passes (the next start-up check then stops it:
    its data folder is a file), so the flag reaches the setting."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SARSHIP_")}
    data = tmp_path / "data"
    argv = [sys.executable, "-m", "sarship", "serve", "--host", "0.0.0.0", "--port", str(free_port())]
    res = subprocess.run([*argv, "--data", str(data)], capture_output=True, text=True, env=env, timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, (res.returncode, res.stderr)
    assert "0.0.0.0" in lines[0] and "SARSHIP_TOKENS" in lines[0] and "--allow-unauthenticated" in lines[0]
    assert not data.exists()
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    res = subprocess.run(
        [*argv, "--allow-unauthenticated", "--data", str(a_file)], capture_output=True, text=True, env=env, timeout=120
    )
    assert res.returncode == 2 and "is not a folder" in res.stderr and "SARSHIP_TOKENS" not in res.stderr, res.stderr


def test_compose_and_systemd_are_safe_by_default(monkeypatch):
    """Compose: the API (every interface of its container, published) needs SARSHIP_TOKENS from
    .env (``${VAR:?}``: compose stops without it), and with none ``serve`` would refuse anyway;
    the dashboard (no tokens) is published on the host's loopback only. systemd: the API
    listens on SARSHIP_HOST, loopback in sarship.env, and the scheduler's dashboard too."""
    from sarship.pipeline.errors import InputError
    from sarship.service.preflight import check_exposure, is_loopback

    doc = _compose()
    api = doc["services"]["api"]
    assert re.fullmatch(r"\$\{SARSHIP_TOKENS:\?[^}]+\}", api["environment"]["SARSHIP_TOKENS"])
    argv = _sarship_argv(api)
    host = argv[argv.index("--host") + 1]
    with pytest.raises(InputError):
        check_exposure(_settings(monkeypatch, SARSHIP_HOST=host))
    check_exposure(_settings(monkeypatch, SARSHIP_HOST=host, SARSHIP_TOKENS='["t"]'))
    assert all(str(p).startswith("127.0.0.1:") for p in doc["services"]["scheduler"]["ports"])

    env = dict(
        line.split("=", 1)
        for line in (DEPLOY / "systemd" / "sarship.env").read_text().splitlines()
        if line and not line.startswith("#")
    )
    unit = (DEPLOY / "systemd" / "sarship-api.service").read_text()
    assert "--host" not in unit and "SARSHIP_TOKENS" not in env
    check_exposure(_settings(monkeypatch, **env))  # loopback: no tokens needed
    assert is_loopback(env["SARSHIP_HOST"]) and is_loopback(env["SARSHIP_DASHBOARD_ADDRESS"].rpartition(":")[0])
    assert "${SARSHIP_DASHBOARD_ADDRESS}" in (DEPLOY / "systemd" / "sarship-scheduler.service").read_text()


# ----------------------------------------------------------------------------- the Dask dashboard

NO_BOKEH = '''import sys


class _NoBokeh:
    """bokeh cannot be imported, as where the 'dashboard' extra is not installed."""

    def find_spec(self, name, path=None, target=None):
        if name == "bokeh" or name.startswith("bokeh."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, _NoBokeh())
'''


def _without_bokeh(tmp_path) -> dict[str, str]:
    """Environment of Python processes without bokeh: a ``sitecustomize`` on PYTHONPATH puts an
    import blocker first on ``sys.meta_path`` in each of them (no code of ours is replaced)."""
    d = tmp_path / "nobokeh"
    d.mkdir()
    (d / "sitecustomize.py").write_text(NO_BOKEH)
    return {"PYTHONPATH": os.pathsep.join(p for p in (str(d), os.environ.get("PYTHONPATH", "")) if p)}


def test_serve_with_tokens_on_every_interface_offers_the_live_dashboard(tmp_path):
    """``sarship serve`` on 0.0.0.0 with tokens starts (reached through 127.0.0.1 only); the
    landing page links the dashboard, GET /dashboard redirects to it and it answers 200 from
    the real scheduler; the start-up line gives its link."""
    pytest.importorskip("bokeh", reason="the 'dashboard' extra (in the test extra)")
    srv = Server(tmp_path / "data", free_port(), SARSHIP_HOST="0.0.0.0", SARSHIP_TOKENS='["s3cret"]').start()
    try:
        links = [x["href"] for x in httpx.get(srv.url + "/").json()["links"]]
        assert f"{srv.url}/dashboard" in links, links
        r = httpx.get(srv.url + "/dashboard", follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"].startswith("http://127.0.0.1:"), r.headers
        page = httpx.get(r.headers["location"])
        assert page.status_code == 200 and "needs bokeh" not in page.text
        assert httpx.delete(srv.url + "/jobs/none").status_code == 401  # the tokens guard it
    finally:
        srv.stop()
    line = [ln for ln in Path(srv.log.name).read_text().splitlines() if "Dask cluster" in ln]
    assert len(line) == 1 and re.search(r"dashboard http://127\.0\.0\.1:\d+/status", line[0]), line


def test_serve_without_bokeh_offers_no_dashboard(tmp_path):
    """Without bokeh (an install without the 'dashboard' extra; ``SARSHIP_ALLOW_UNAUTHENTICATED``
    lets it serve on 0.0.0.0): no dashboard link on the landing page, GET /dashboard a 404
    problem saying how to enable it (no server path), and the start-up line (the one
    ``sarship detect`` prints) gives no link but the same hint."""
    srv = Server(
        tmp_path / "data",
        free_port(),
        SARSHIP_HOST="0.0.0.0",
        SARSHIP_ALLOW_UNAUTHENTICATED="1",
        **_without_bokeh(tmp_path),
    ).start()
    try:
        links = [x["href"] for x in httpx.get(srv.url + "/").json()["links"]]
        assert not [h for h in links if "dashboard" in h], links
        r = httpx.get(srv.url + "/dashboard", follow_redirects=False)
        check_problem(r, 404, "sarship[dashboard]")
        assert str(tmp_path) not in r.text
    finally:
        srv.stop()
    line = [ln for ln in Path(srv.log.name).read_text().splitlines() if "Dask cluster" in ln]
    assert len(line) == 1 and "no dashboard" in line[0] and "sarship[dashboard]" in line[0], line
    assert "http" not in line[0], line
    from sarship.workers.cluster import dashboard_serves

    assert not dashboard_serves(f"http://127.0.0.1:{free_port()}/status", timeout=1)  # nothing listens there


def test_detect_without_bokeh_prints_no_dashboard_link(tmp_path):
    """``sarship detect`` where bokeh cannot be imported: its cluster line offers no link but
    says how to get one, and run.json records no dashboard."""
    scene = tmp_path / "s.zarr"
    write_scene(scene, {"intensity": blobs_scene((96, 96), looks=2.0, seed=2, n=2)}, tile=96, looks=2.0)
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": "", **_without_bokeh(tmp_path)}
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "sarship",
            "detect",
            str(scene),
            "--detector",
            "ca_cfar",
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    line = [ln for ln in res.stderr.splitlines() if "Dask cluster" in ln]
    assert len(line) == 1 and "no dashboard" in line[0] and "sarship[dashboard]" in line[0], res.stderr
    assert "http" not in line[0], line
    assert json.loads((tmp_path / "out" / "run.json").read_text())["cluster"]["dashboard"] is None
