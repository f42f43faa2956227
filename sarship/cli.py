"""The ``sarship`` command line (docs/interfaces/cli.md).

Every command: ``--help``; exit 0 on success; exit 2 with one line on stderr naming the
problem for bad input or arguments (no traceback; nothing partial left behind); long work
shows progress on stderr. ``SARSHIP_DEBUG=1`` prints tracebacks of unexpected errors.

The commands that write outputs (``simulate``, ``ingest``, ``detect``, ``demo``) end in
order on SIGTERM as on Ctrl-C: the signal unwinds the command (``SystemExit(143)``), so that
its temporary outputs (``.NAME.partial-*``, ``.sarship-partial-*``) are removed; exit 143.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import sys
from pathlib import Path
from typing import Any

from sarship.pipeline import settings as env_settings
from sarship.pipeline.errors import InputError
from sarship.pipeline.readers.limits import (
    DEFAULT_MAX_CHUNK_MB,
    DEFAULT_MAX_PIXELS,
    DEFAULT_MAX_RATIO,
    DEFAULT_MAX_XML_MB,
)
from sarship.pipeline.scene import DEFAULT_INGEST_CODEC, INGEST_CODECS
from sarship.temporaries import present, remove_new, temporaries
from sarship.workers.request import DEVICES


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, epilog_fn=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._epilog_fn = epilog_fn  # an epilog computed only when help is shown (start-up time)

    def format_help(self) -> str:
        if self._epilog_fn is not None:
            self.epilog, self._epilog_fn = self._epilog_fn(), None
        return super().format_help()

    def error(self, message: str):  # one line, exit 2 (argparse prints usage + error)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _shape(text: str) -> tuple[int, int]:
    try:
        a, b = text.lower().split("x")
        return int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROWSxCOLS like 2048x2048, got '{text}'") from None


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got '{text}'")
    return v


def _settings(pairs: list[str]) -> dict[str, str]:
    out = {}
    for p in pairs or []:
        if "=" not in p:
            raise InputError(f"--set expects KEY=VALUE, got '{p}'")
        k, v = p.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _spacing(text: str) -> tuple[float, float]:
    """``AZ,RG`` metres: two positive numbers."""
    import math

    try:
        az, rg = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected AZ,RG (two positive numbers of metres, e.g. 2.3,13.9), got '{text}'"
        ) from None
    if not (math.isfinite(az) and math.isfinite(rg) and az > 0 and rg > 0):
        raise argparse.ArgumentTypeError(f"expected two positive numbers of metres, got '{text}'")
    return az, rg


def _lonlat(text: str) -> tuple[float, float]:
    """``LON,LAT`` degrees (WGS84)."""
    import math

    try:
        lon, lat = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected LON,LAT (two numbers of degrees, e.g. 10.6,59.8), got '{text}'"
        ) from None
    if not (math.isfinite(lon) and math.isfinite(lat) and -180 <= lon <= 180 and -80 <= lat <= 80):
        raise argparse.ArgumentTypeError(f"expected lon in [-180, 180] and lat in [-80, 80], got '{text}'")
    return lon, lat


def _print_warnings(command: str, run: dict) -> None:
    """Every entry of run.json's "warnings", one line each on stderr."""
    for w in run.get("warnings") or []:
        print(f"sarship {command}: warning: {w}", file=sys.stderr)


def _progress(label: str):
    from sarship.workers.progress import Progress

    return Progress.callback(label)


# ----------------------------------------------------------------------------- commands


def cmd_simulate(a) -> int:
    from sarship.pipeline.simulate import SimConfig, simulate, validate

    if a.ais is not None and a.geo is None:
        raise InputError("--ais needs --geo LON,LAT: AIS reports are lon/lat positions")
    if a.dark_fraction is not None and a.ais is None:
        raise InputError("--dark-fraction needs --ais FILE.csv")
    ais = {"ais": True, **({} if a.dark_fraction is None else {"dark_fraction": a.dark_fraction})} if a.ais else {}
    cfg = validate(
        SimConfig(
            kind=a.kind,
            shape=a.shape,
            ships=a.ships,
            seed=a.seed,
            looks=a.looks,
            clutter=a.clutter,
            land=a.land,
            sidelobes=a.sidelobes,
            ambiguities=a.ambiguities,
            stripes=a.stripes,
            rfi=a.rfi,
            scr_db=a.scr_db,
            pixel_spacing_m=(a.spacing, a.spacing),
            texture_shape=a.texture_shape,
            ggd_power=a.ggd_power,
            ggd_shape=a.ggd_shape,
            shape_beta=a.shape_beta,
            geo=a.geo,
            geo_gcps=a.geo_gcps,
            time=a.time,
            moving=a.moving,
            **ais,
        )
    )
    out = Path(a.out)
    truth = a.truth or f"{out}.truth.geojson"
    simulate(
        out,
        cfg,
        tile=a.tile,
        truth_path=truth,
        progress=_progress("simulate"),
        overwrite=a.overwrite,
        ais_path=a.ais,
    )
    print(f"scene: {out}")
    print(f"truth: {truth}")
    if a.ais:
        print(f"ais: {a.ais}")
    return 0


def cmd_ingest(a) -> int:
    from sarship.pipeline.readers import InputLimits, ingest

    channels = a.channels.split(",") if a.channels else None
    band: Any = a.band
    if band is not None and band.isdigit():
        band = int(band)
    limits = InputLimits(
        max_pixels=a.max_pixels, max_chunk_mb=a.max_chunk_mb, max_ratio=a.max_ratio, max_xml_mb=a.max_xml_mb
    )
    scene = ingest(
        a.inputs,
        a.out,
        kind=a.kind,
        tile=a.tile,
        progress=_progress("ingest"),
        band=band,
        channels=channels,
        looks=a.looks,
        overwrite=a.overwrite,
        spacing=a.spacing,
        limits=limits,
        swath=a.swath,
        codec=a.codec,
    )
    cal = str(scene.attrs.get("calibration", ""))
    if cal.startswith("none"):  # a SAFE product without calibration annotation: DN^2, not sigma0
        print(f"warning: calibration {cal}: samples are DN^2", file=sys.stderr)
    print(
        f"scene: {scene.path} {scene.shape[0]}x{scene.shape[1]} kind={scene.kind} "
        f"looks={scene.looks} variables={','.join(scene.variables)}"
    )
    return 0


def _scheduler(given: str | None) -> str | None:
    """``--scheduler`` of a batch command: the given address, else ``SARSHIP_SCHEDULER`` (the
    service's setting: a cluster kept running, whose warm workers skip the local cluster's
    start-up), else None (a local cluster). ``local`` always means a local cluster."""
    value = (given if given is not None else env_settings.read("scheduler") or "").strip()
    return None if value in ("", "local") else value


def cmd_detect(a) -> int:
    from sarship import warm_process
    from sarship.workers.jobs import run_detection

    extra = _formats(a.formats, a.scene)  # checked before the run: a missing extra fails at once
    scheduler = _scheduler(a.scheduler)
    client = warm_process.active_client() if scheduler is None else None  # in the warm process (sarship warm)
    note = None
    if client is not None:
        from sarship.workers.cluster import dashboard_note

        note = f"sarship: warm cluster, {warm_process.active_description()}, {dashboard_note(client)}"
    settings = _settings(a.set)
    if a.ais:
        settings["ais"] = a.ais
    run = run_detection(
        a.scene,
        a.detector,
        settings,
        out_dir=a.out,
        tile=a.tile,
        client=client,
        scheduler=scheduler,
        device=a.device,
        progress=True,
        overwrite=a.overwrite,
        cluster_note=note,
    )
    _print_warnings("detect", run)
    o = run["outputs"]
    print(f"detections: {o['detections.geojson']} ({run['detections']} ships)")
    for fmt in extra:  # converted from detections.geojson (pipeline/products/export.py)
        from sarship.pipeline.products.export import export

        dst = Path(o["detections.geojson"]).with_suffix(f".{fmt}")
        export(o["detections.geojson"], dst, overwrite=True)  # the run's own folder, just written
        print(f"{fmt}: {dst}")
    print(f"mask: {o['mask.zarr']}")
    if "ais" in run:
        _print_ais(run["ais"], o.get("ais_unmatched.geojson"))
    print(f"run: {o['run.json']}")
    return 0


def _print_ais(rec: dict, unmatched_path: str | None) -> None:
    """The AIS stage's summary line (run.json ``ais``)."""
    dark = "dark: unknown (the AIS given does not cover the scene)" if rec["dark"] is None else f"{rec['dark']} dark"
    rejected = rec["read"]["rejected"]
    print(
        f"ais: {rec['matched']} of {rec['detections']} detections matched, {dark}; "
        f"{rec['unmatched_in_footprint']} reporting vessels unmatched: {unmatched_path}"
        + (f" ({rejected} AIS lines or messages rejected)" if rejected else "")
    )


def _formats(text: str | None, scene: str) -> list[str]:
    """``--formats geojson,gpkg,kml``: the extra formats (GeoJSON is always written), checked
    before any work: known names, the ``gis`` extra installed, the scene georeferenced."""
    names = [t.strip().lower() for t in (text or "geojson").split(",") if t.strip()]
    bad = [n for n in names if n not in ("geojson", "gpkg", "kml")]
    if bad:
        raise InputError(f"--formats: unknown format {bad[0]!r} (geojson, gpkg, kml)")
    extra = list(dict.fromkeys(n for n in names if n != "geojson"))
    if extra:
        from sarship.pipeline.products.export import require_pyogrio
        from sarship.pipeline.scene import open_scene

        require_pyogrio()
        attrs = open_scene(scene).attrs
        if not (attrs.get("gcps") or (attrs.get("crs") and attrs.get("transform") is not None)):
            raise InputError(
                f"--formats {','.join(extra)}: '{scene}' is not georeferenced (no crs + transform "
                "or GCPs): its detections have no WGS84 outlines to map"
            )
    return extra


def cmd_match(a) -> int:
    from sarship.pipeline.run.rematch import rematch

    rec = rematch(a.run_dir, a.ais, overwrite=a.overwrite)
    run_dir = Path(a.run_dir)
    _print_ais(rec, str((run_dir / "ais_unmatched.geojson").resolve()))
    print(f"detections: {(run_dir / 'detections.geojson').resolve()}")
    return 0


def cmd_export(a) -> int:
    from sarship.pipeline.products.export import export

    n = export(a.detections, a.to, overwrite=a.overwrite)
    print(f"{a.to}: {n} {'vessels' if Path(a.detections).name.startswith('ais_unmatched') else 'ships'}")
    return 0


def cmd_enhance(a) -> int:
    from sarship.pipeline.image.destripe import DestripeParams
    from sarship.workers.enhance import run_enhance

    if not a.destripe:
        raise InputError("nothing to do: pass --destripe (the only enhancement of this version)")
    params = DestripeParams(stripes_along=a.stripes_along, segment=a.segment, z_min=a.z_min)
    rec = run_enhance(a.scene, a.out, params, scheduler=_scheduler(a.scheduler), progress=True, overwrite=a.overwrite)
    d = rec["destripe"]
    print(f"scene: {a.out}")
    print(
        f"destripe: {len(d['stop_bins'])} stopped bins, {len(d['lines'])} Hough lines, "
        f"stripe rms {d['stripe_rms_db']:.3f} dB"
    )
    return 0


def cmd_worker(a) -> int:
    from sarship.workers.worker import serve

    return serve(
        a.scheduler,
        gpus=a.gpus,
        cpus=a.cpus,
        name=a.name,
        memory_limit=a.memory_limit,
        gpu_threads=a.gpu_threads,
        gpu_procs=a.gpu_procs,
    )


def cmd_warm(a) -> int:
    from sarship import warm

    if a.workers is not None and a.workers < 0:
        raise InputError(f"--workers must be 0 or more, got {a.workers}")
    try:
        if a.action == "run":
            from sarship.warm_process import CommandLine, serve

            return serve(
                CommandLine(parser=build_parser, main=main),
                device=a.device,
                workers=a.workers,
                idle_timeout=a.idle_timeout,
                dashboard=a.dashboard,
                warm_up=a.warm_up,
            )
        if a.action == "start":
            state = warm.start(
                device=a.device,
                workers=a.workers,
                idle_timeout=a.idle_timeout,
                dashboard=a.dashboard,
                warm_up=a.warm_up,
            )
            print(
                f"sarship: warm cluster ready (pid {state['pid']}): {state['what']}, dashboard "
                f"{state['dashboard']}, ends after {a.idle_timeout:g} s without a command; socket {state['socket']}"
            )
            return 0
        if a.action == "status":
            state = warm.status()
            if state is None:
                print(f"no warm cluster (socket {warm.socket_path()})")
                return 1
            idle = (
                "never ends by itself"
                if not state["idle_timeout_s"]
                else f"ends after {state['idle_timeout_s']:g} s without a command"
            )
            print(
                f"warm cluster (pid {state['pid']}): {state['what']}, dashboard {state['dashboard']}, "
                f"{state['commands']} commands run, {idle}; socket {state['socket']}"
            )
            return 0
        state = warm.stop()
        print("no warm cluster was running" if state is None else f"warm cluster (pid {state['pid']}) stopped")
        return 0
    except warm.WarmError as exc:
        raise InputError(str(exc)) from None


def _idle(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of seconds >= 0 (0: never), got '{text}'")
    return value


def _warm_up_list(text: str) -> tuple[str, ...]:
    from sarship.pipeline.detectors import names as known

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    if names in ((), ("none",)):
        return ()
    unknown = [n for n in names if n not in known()]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown detector '{unknown[0]}' (known: {', '.join(known())}; or none)")
    return names


def cmd_serve(a) -> int:
    from pydantic import ValidationError

    from sarship.service.settings import Settings

    over = {
        k: v
        for k, v in {
            "host": a.host,
            "port": a.port,
            "scheduler": a.scheduler,
            "data": a.data,
            "workers": a.workers,
            "worker_threads": a.worker_threads or None,
            "gpus": a.gpus,
            "concurrency": a.concurrency,
            "inbox": a.inbox,
            "inbox_interval_s": a.inbox_interval,
            "inbox_cron": a.inbox_cron,
            "inbox_detectors": a.inbox_detectors,
            "inbox_settle_s": a.inbox_settle,
            "inbox_quarantine": a.inbox_quarantine,
            "inbox_ais": a.inbox_ais,
            "allow_unauthenticated": a.allow_unauthenticated or None,
        }.items()
        if v is not None
    }
    try:
        settings = Settings(**over)
    except ValidationError as exc:
        e = exc.errors()[0]
        raise InputError(f"setting '{'.'.join(str(x) for x in e['loc'])}': {e['msg']}") from None
    from sarship.service.preflight import preflight

    preflight(settings)  # a bad data folder, store, address or scheduler: one line, exit 2
    import uvicorn

    from sarship.service.app import create_app

    print(f"sarship: serving on http://{settings.host}:{settings.port} (data {settings.data})", file=sys.stderr)
    app = create_app(settings)
    # requests still open at SIGTERM get 10 s to finish (a 'Prefer: respond-sync' wait ends at
    # once: it answers 201 with the job's status, the job stays in the store)
    server = uvicorn.Server(
        uvicorn.Config(app, host=settings.host, port=settings.port, log_level="warning", timeout_graceful_shutdown=10)
    )
    app.state.should_exit = lambda: server.should_exit
    server.run()
    return 0 if server.started else 3  # (uvicorn.run's exit status when the app could not start)


def cmd_evaluate(a) -> int:
    from sarship.pipeline.products.scoring import evaluate, format_scores

    det = Path(a.detections)
    mask = a.mask
    if mask is None and (det.parent / "mask.zarr").exists():
        mask = str(det.parent / "mask.zarr")
    scores = evaluate(det, a.truth, mask_path=mask, ignore_flagged=a.ignore_flagged)
    if a.json:
        print(json.dumps(scores, indent=1))
    else:
        print(format_scores(scores))
    return 0


def cmd_detectors(a) -> int:
    from sarship.pipeline import detectors

    info = [detectors.get(n).describe() for n in detectors.names()]
    if a.json:
        print(json.dumps(info, indent=1, default=str))
        return 0
    for d in info:
        print(f"{d['name']}: {d['summary']}")
        print(f"  input: {d['input']}; halo: {d['halo']} ({d['halo_default_px']} px by default)")
        print(f"  reference: {d['reference']}")
        for k, p in d["parameters"].items():
            print(f"  {k} = {d['defaults'][k]!r}: {p.get('description', '')}")
    return 0


def cmd_demo(a) -> int:
    """Simulate a scene with ships, detect them on a local Dask cluster, score them."""
    from sarship.pipeline.products.scoring import evaluate, format_scores
    from sarship.pipeline.simulate import SimConfig, simulate, validate
    from sarship.workers.jobs import run_detection

    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out '{out}' exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not a.overwrite:
        raise InputError(
            f"output folder '{out}' exists and is not empty: pass --overwrite to replace "
            "the demo's outputs in it, or choose another folder"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder '{out}': {exc.strerror}") from None
    scene = out / "scene.zarr"
    truth = out / "scene.truth.geojson"
    cfg = validate(
        SimConfig(
            kind="intensity",
            shape=a.shape,
            ships=a.ships,
            seed=a.seed,
            looks=a.looks,
            clutter="k",
            scr_db=a.scr_db,
            pixel_spacing_m=(a.spacing, a.spacing),
            length_m=(40.0, 350.0),
        )
    )
    print(
        f"sarship demo: simulating a {a.shape[0]}x{a.shape[1]} K-distributed sea ({a.looks:g} looks, "
        f"{a.spacing:g} m pixels) with {a.ships} ships of 40-350 m at SCR {a.scr_db:g} dB",
        file=sys.stderr,
    )
    simulate(scene, cfg, tile=a.tile, truth_path=truth, progress=_progress("simulate"))
    run = run_detection(
        scene,
        a.detector,
        _settings(a.set),
        out_dir=out / "detect",
        tile=a.tile,
        scheduler=a.scheduler,
        progress=True,
        overwrite=a.overwrite,
    )
    _print_warnings("demo", run)
    det = out / "detect" / "detections.geojson"
    scores = evaluate(det, truth)
    from sarship.pipeline.targets.ship_features import write_json

    write_json(out / "scores.json", scores)
    print(format_scores(scores))
    print(f"scene: {scene}")
    print(f"truth: {truth}")
    print(f"detections: {det} ({run['detections']} ships)")
    print(f"mask: {out / 'detect' / 'mask.zarr'}")
    print(f"run: {out / 'detect' / 'run.json'}")
    print(f"scores: {out / 'scores.json'}")
    return 0


# ----------------------------------------------------------------------------- parser


def _settings_help() -> str:
    """Every service setting with its environment variable, default and meaning, generated from
    :class:`sarship.service.settings.Settings` so that ``sarship serve --help`` cannot fall behind it."""
    import textwrap

    from pydantic_core import PydanticUndefined

    from sarship.service.settings import Settings

    lines = ["settings (environment variable: default, meaning):"]
    for name, f in Settings.model_fields.items():
        if f.default_factory is not None:
            default = repr(f.default_factory())
        elif f.default is PydanticUndefined:
            default = "required"
        else:
            default = "none" if f.default is None else str(f.default)
        lines.append(f"  SARSHIP_{name.upper()}: {default}")
        lines += textwrap.wrap(f.description or "", width=88, initial_indent="      ", subsequent_indent="      ")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="sarship", description="Ship detection in SAR scenes on Dask (see docs/interfaces/cli.md).")
    p.add_argument("--version", action="version", version=f"sarship {__import__('sarship').__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    _parser_simulate(sub)
    _parser_ingest(sub)
    _parser_detect(sub)
    _parser_warm(sub)
    _parser_export(sub)
    _parser_enhance(sub)
    _parser_worker(sub)
    _parser_serve(sub)
    _parser_evaluate(sub)
    _parser_detectors(sub)
    _parser_demo(sub)
    return p


def _parser_simulate(sub) -> None:
    """``sarship simulate``'s options."""
    s = sub.add_parser("simulate", help="simulate a scene with ground truth")
    s.add_argument("out", help="output scene store (OUT.zarr)")
    s.add_argument("--kind", choices=["intensity", "slc", "quadpol"], default="intensity")
    s.add_argument("--shape", type=_shape, default=(2048, 2048), help="ROWSxCOLS (default 2048x2048)")
    s.add_argument("--ships", type=int, default=10)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--looks", type=float, default=1.0)
    s.add_argument("--clutter", choices=["rayleigh", "gamma", "k", "g0", "ggd", "cggd"], default="gamma")
    s.add_argument(
        "--texture-shape",
        dest="texture_shape",
        type=float,
        default=4.0,
        help="k: gamma texture shape nu; g0: inverse-gamma texture shape a = -alpha > 1 (default 4)",
    )
    s.add_argument(
        "--ggd-power",
        dest="ggd_power",
        type=float,
        default=0.7,
        help="ggd: power v of the generalized gamma (default 0.7)",
    )
    s.add_argument(
        "--ggd-shape",
        dest="ggd_shape",
        type=float,
        default=3.0,
        help="ggd: shape kappa of the generalized gamma (default 3)",
    )
    s.add_argument(
        "--shape-beta",
        dest="shape_beta",
        type=float,
        default=1.0,
        help="cggd (--kind slc): complex generalized Gaussian shape beta, 1 = complex Gaussian, "
        "< 1 super-Gaussian, > 1 sub-Gaussian (default 1)",
    )
    s.add_argument("--scr-db", dest="scr_db", type=float, default=15.0, help="ship-to-clutter ratio (dB)")
    s.add_argument("--spacing", type=float, default=10.0, help="pixel spacing in metres (default 10)")
    flag_help = {
        "ambiguities": "azimuth ghosts (k = +-1, -20 dB) of every ship where the scene's sar_geometry puts "
        "them (docs/algorithms/ambiguity.md)"
    }
    for flag in ("land", "sidelobes", "ambiguities", "stripes", "rfi"):
        s.add_argument(f"--{flag}", action="store_true", help=flag_help.get(flag))
    s.add_argument(
        "--geo",
        type=_lonlat,
        metavar="LON,LAT",
        help="georeference the scene (WGS84, north-up, centred on LON,LAT, --spacing metres a pixel); "
        "with --land the land is the GSHHG shoreline's (needs pip install 'sarship[coastline]')",
    )
    s.add_argument(
        "--geo-gcps",
        dest="geo_gcps",
        action="store_true",
        help="with --geo: store the georeference as a 6 x 6 grid of GCPs instead of an affine transform",
    )
    s.add_argument(
        "--time",
        metavar="ISO",
        help="first line time, ISO 8601 UTC (default: a fixed time derived from --seed)",
    )
    s.add_argument(
        "--moving",
        action="store_true",
        help="ships under way (30%% at anchor or drifting at 0-1 kn, the others 2-25 kn, COG along the bow), "
        "imaged at their azimuth-displaced position R v_toward / V (docs/ais.md)",
    )
    s.add_argument(
        "--ais",
        metavar="FILE.csv",
        help="with --geo: write the ships' AIS reports (plain AIS CSV, +-10 min) there, plus AIS vessels "
        "outside the swath and too small to see; the truth gets each ship's mmsi and dark flag",
    )
    s.add_argument(
        "--dark-fraction",
        dest="dark_fraction",
        type=float,
        metavar="F",
        help="with --ais: the fraction of the ships that never report (default 0.2)",
    )
    s.add_argument("--truth", help="truth GeoJSON path (default OUT.zarr.truth.geojson)")
    s.add_argument("--tile", type=_positive_int, default=2048)
    s.add_argument("--overwrite", action="store_true", help="replace an existing scene store, truth file and AIS file")
    s.set_defaults(func=cmd_simulate)


def _parser_ingest(sub) -> None:
    """``sarship ingest``'s options."""
    s = sub.add_parser(
        "ingest",
        help="convert GeoTIFF/TIFF, PNG/JPEG, .npy, a Sentinel-1 GRD or IW SLC SAFE "
        "(folder or .zip) or Zarr into a scene store",
    )
    s.add_argument("inputs", nargs="+")
    s.add_argument("--out", required=True, help="output scene store (SCENE.zarr)")
    s.add_argument("--kind", choices=["auto", "amplitude", "intensity", "slc", "quadpol", "covariance"], default="auto")
    s.add_argument("--tile", type=_positive_int, default=2048)
    s.add_argument("--channels", help="comma-separated channel names of the bands/files (e.g. vh,vv)")
    s.add_argument("--band", help="band (name or index) used as 'intensity' for multi-band real inputs")
    s.add_argument("--looks", type=float, help="equivalent number of looks (default: from the product or estimated)")
    s.add_argument(
        "--spacing",
        type=_spacing,
        metavar="AZ,RG",
        help="pixel spacing in metres, azimuth,range (overrides the product's)",
    )
    s.add_argument("--overwrite", action="store_true", help="replace an existing scene store at --out")
    s.add_argument(
        "--codec",
        choices=list(INGEST_CODECS),
        default=DEFAULT_INGEST_CODEC,
        help="compressor of the store: auto (default: zstd when it stores a sample of the pixels in "
        "at most 1/1.2 of their bytes, else none), zstd, lz4 (Blosc LZ4 + byte shuffle), none",
    )
    s.add_argument(
        "--swath",
        metavar="IW1|IW2|IW3",
        help="sub-swath of a Sentinel-1 IW SLC product (one scene per sub-swath; required when it has several)",
    )
    s.add_argument(
        "--max-pixels",
        type=float,
        default=DEFAULT_MAX_PIXELS,
        help=f"refuse an input declaring more rows x columns (default {DEFAULT_MAX_PIXELS:.3g})",
    )
    s.add_argument(
        "--max-chunk-mb",
        type=float,
        default=DEFAULT_MAX_CHUNK_MB,
        help=f"refuse a compressed TIFF strip/tile decoding to more MiB (default {DEFAULT_MAX_CHUNK_MB:g})",
    )
    s.add_argument(
        "--max-ratio",
        type=float,
        default=DEFAULT_MAX_RATIO,
        help="refuse a compressed/sparse TIFF declaring more decoded bytes per file byte "
        f"(default {DEFAULT_MAX_RATIO:g})",
    )
    s.add_argument(
        "--max-xml-mb",
        type=float,
        default=DEFAULT_MAX_XML_MB,
        help="refuse a Sentinel-1 SAFE product with an XML member (annotation, manifest...) of more MiB "
        f"(default {DEFAULT_MAX_XML_MB:g})",
    )
    s.set_defaults(func=cmd_ingest)


def _parser_detect(sub) -> None:
    """``sarship detect``'s options."""
    s = sub.add_parser("detect", help="run a detector on a scene store")
    s.add_argument("scene")
    s.add_argument(
        "--detector",
        required=True,
        help="detector name (sarship detectors), or auto: the simplest of ca_cfar, k_cfar, g0_cfar "
        "whose clutter model fits the scene (measured first; run.json detector_auto)",
    )
    s.add_argument("--set", action="append", metavar="KEY=VALUE", help="detector parameter (repeatable)")
    s.add_argument("--out", default="sarship-out", help="output folder (default ./sarship-out)")
    s.add_argument(
        "--tile",
        type=_positive_int,
        help="processing tile side (default: the scene's tile, doubled up to 4096 "
        "while the scene keeps at least 32 tiles)",
    )
    s.add_argument(
        "--scheduler",
        help="address of an existing Dask scheduler (default: $SARSHIP_SCHEDULER if set, "
        "else the warm cluster if one runs (sarship warm), else start a local "
        "cluster; 'local': a local cluster of this command's own)",
    )
    s.add_argument("--device", choices=list(DEVICES), default="auto")
    s.add_argument(
        "--overwrite",
        action="store_true",
        help="write into an existing non-empty --out folder, replacing its detections.geojson, mask.zarr and run.json",
    )
    s.add_argument(
        "--formats",
        metavar="LIST",
        default="geojson",
        help="detection files to write, comma-separated: geojson (always), gpkg (GeoPackage), kml; "
        "gpkg/kml need a georeferenced scene and the extra: pip install 'sarship[gis]'",
    )
    s.add_argument(
        "--ais",
        action="append",
        metavar="FILE",
        help="AIS file matched to the detections (repeatable): NMEA, MarineCadastre, Danish Maritime Authority "
        "or plain CSV, plain or compressed (docs/ais.md); needs a georeferenced scene with a time",
    )
    s.set_defaults(func=cmd_detect)


def _parser_warm(sub) -> None:
    """``sarship warm``'s options."""
    s = sub.add_parser(
        "warm",
        help="keep a local cluster running between sarship detect commands (start, status, "
        "stop; docs/interfaces/cli.md)",
    )
    s.add_argument(
        "action",
        choices=["start", "status", "stop", "run"],
        help="start: in the background; status; stop (after the command it runs); run: in the foreground",
    )
    s.add_argument(
        "--device",
        choices=list(DEVICES),
        default="auto",
        help="auto (default): the GPUs' worker processes when there are GPUs, plus CPU workers on the "
        "other cores; gpu: refuse to start without a GPU; cpu: CPU workers only",
    )
    s.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="CPU worker processes (default: one per core, less the GPU worker processes)",
    )
    s.add_argument(
        "--idle-timeout",
        dest="idle_timeout",
        type=_idle,
        default=900.0,
        metavar="S",
        help="end after S seconds without a command (default 900; 0: never)",
    )
    s.add_argument(
        "--dashboard",
        default="127.0.0.1:8787",
        help="the Dask dashboard's address (default 127.0.0.1:8787; another free port if taken)",
    )
    s.add_argument(
        "--warm-up",
        dest="warm_up",
        type=_warm_up_list,
        default=("ca_cfar",),
        metavar="LIST",
        help="detectors run once on a small simulated scene at the start, so that the first command "
        "finds their compiled kernels loaded in every worker (comma-separated; default ca_cfar; "
        "none)",
    )
    s.set_defaults(func=cmd_warm)


def _parser_export(sub) -> None:
    """``sarship export``'s options."""
    s = sub.add_parser(
        "match",
        help="match a finished run's detections to AIS files again, without detecting again (docs/ais.md)",
    )
    s.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of sarship detect (or a service job's)")
    s.add_argument(
        "--ais", action="append", required=True, metavar="FILE", help="AIS file (repeatable; formats: docs/ais.md)"
    )
    s.add_argument(
        "--overwrite", action="store_true", help="match again a run already matched (replaces its AIS results)"
    )
    s.set_defaults(func=cmd_match)
    s = sub.add_parser(
        "export",
        help="detections.geojson (or ais_unmatched.geojson) as a GeoPackage (.gpkg) or KML (.kml) file for a GIS",
    )
    s.add_argument(
        "detections",
        help="a detections.geojson written by sarship detect or the service, or a run's ais_unmatched.geojson",
    )
    s.add_argument("--to", required=True, metavar="FILE", help="FILE.gpkg or FILE.kml (the suffix picks the format)")
    s.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    s.set_defaults(func=cmd_export)


def _parser_enhance(sub) -> None:
    """``sarship enhance``'s options."""
    s = sub.add_parser("enhance", help="image-quality enhancement into a new scene store (--destripe)")
    s.add_argument("scene")
    s.add_argument("--out", required=True, help="output scene store (OUT.zarr); never the input")
    s.add_argument("--destripe", action="store_true", help="remove stripe noise (docs/algorithms/destripe.md)")
    s.add_argument(
        "--stripes-along",
        dest="stripes_along",
        choices=["azimuth", "range"],
        default="azimuth",
        help="the axis along which the stripe gain is constant (default azimuth)",
    )
    s.add_argument("--segment", type=_positive_int, default=32, help="lines per segment of the stripe spectrum")
    s.add_argument(
        "--z-min", dest="z_min", type=float, default=4.0, help="noise floor of the stripe coherence ratio (default 4)"
    )
    s.add_argument(
        "--scheduler",
        help="address of an existing Dask scheduler (default: $SARSHIP_SCHEDULER if set, "
        "else start a local cluster; 'local': a local cluster)",
    )
    s.add_argument("--overwrite", action="store_true", help="replace an existing scene store at --out")
    s.set_defaults(func=cmd_enhance)


def _parser_worker(sub) -> None:
    """``sarship worker``'s options."""
    s = sub.add_parser(
        "worker", help="start this machine's Dask workers for a scheduler: one per GPU, plus CPU workers"
    )
    s.add_argument("--scheduler", required=True, help="scheduler address, e.g. tcp://10.0.0.1:8786")
    s.add_argument("--gpus", default="all", help="all (default), none, or a comma list of GPU IDs (0,1)")
    s.add_argument(
        "--cpus",
        type=int,
        default=None,
        help="single-threaded CPU worker processes (default: all cores without GPUs, else 0)",
    )
    s.add_argument(
        "--gpu-threads",
        type=int,
        default=2,
        help="tiles a GPU worker runs at once (default 2: one tile's Zarr I/O overlaps the "
        "other's GPU work; 1: strictly one)",
    )
    s.add_argument(
        "--gpu-procs",
        type=int,
        default=None,
        help="worker processes per GPU (default: SARSHIP_GPU_PROCS, else a quarter of the cores "
        "per GPU, at most 4 per GPU and 4 in all, as sarship detect's local cluster): each runs the Python parts "
        "of its tiles (Zarr read/write, labelling) on its own core",
    )
    s.add_argument("--name", help="worker name prefix (default: the host name)")
    s.add_argument("--memory-limit", help="per-worker memory limit, e.g. 8GiB (default: Dask's auto)")
    s.set_defaults(func=cmd_worker)


def _parser_serve(sub) -> None:
    """``sarship serve``'s options."""
    s = sub.add_parser(
        "serve",
        help="the job API (OGC API - Processes shape) with a local Dask cluster or "
        "--scheduler; settings also from SARSHIP_* environment variables",
        description="Every setting is a flag below or a SARSHIP_* environment variable "
        "(flags win); the full list follows.",
        epilog_fn=_settings_help,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument(
        "--host",
        help="address to listen on (default 127.0.0.1); an address other machines reach "
        "needs tokens (SARSHIP_TOKENS) or --allow-unauthenticated",
    )
    s.add_argument("--port", type=int)
    s.add_argument(
        "--allow-unauthenticated",
        action="store_true",
        help="serve without tokens on an address other machines reach (refused otherwise)",
    )
    s.add_argument("--scheduler", help="Dask scheduler address (default: start a local cluster)")
    s.add_argument("--data", help="data folder (default ./sarship-data)")
    s.add_argument(
        "--workers",
        type=_positive_int,
        help="local cluster CPU worker processes (default: all cores; with GPU workers, all cores less two per GPU)",
    )
    s.add_argument(
        "--worker-threads",
        action="store_true",
        help="local cluster CPU workers as threads of this process instead of worker processes "
        "(starts in about a second; for small deployments and tests)",
    )
    s.add_argument(
        "--gpus",
        help="local cluster GPUs: all (default: one pinned worker per visible GPU), none, "
        "or a comma list of GPU IDs (0,1)",
    )
    s.add_argument("--concurrency", type=_positive_int, help="jobs run at once by this API process (default 2)")
    s.add_argument(
        "--inbox",
        action="append",
        metavar="FOLDER",
        help="inbox folder watched for new passes (repeat for several); new files are ingested once "
        "(scene id = content hash) and the --inbox-detectors jobs submitted for them",
    )
    s.add_argument("--inbox-interval", type=float, metavar="SECONDS", help="seconds between inbox scans (default 30)")
    s.add_argument(
        "--inbox-cron",
        metavar="EXPR",
        help="cron expression of the inbox scans, in UTC (instead of an interval), e.g. '*/10 * * * *'",
    )
    s.add_argument(
        "--inbox-detectors",
        metavar="SPEC",
        help='detector jobs for each new pass: a JSON list like \'[{"detector": "os_cfar", '
        '"pfa": 1e-6}]\' or a comma list of names (default: none, ingest only)',
    )
    s.add_argument(
        "--inbox-settle",
        type=float,
        metavar="SECONDS",
        help="take a file once its size and mtime are unchanged this long (default 5), or at once "
        "when FILE.done exists and is not older than the file (the marker is removed then)",
    )
    s.add_argument(
        "--inbox-quarantine",
        metavar="FOLDER",
        help="where files that fail to ingest go, with NAME.reason.txt (default DATA/quarantine)",
    )
    s.add_argument(
        "--inbox-ais",
        metavar="FOLDER",
        help="folder of AIS files each new pass's detector jobs are matched with (the newest "
        "first, within SARSHIP_INBOX_AIS_MAX_FILES and _MAX_MB; docs/ais.md); outside the inboxes",
    )
    s.set_defaults(func=cmd_serve)


def _parser_evaluate(sub) -> None:
    """``sarship evaluate``'s options."""
    s = sub.add_parser("evaluate", help="score detections against truth")
    s.add_argument("detections")
    s.add_argument("--truth", required=True, help="truth GeoJSON, PASCAL-VOC xml (file or folder) or mask image")
    s.add_argument("--mask", help="detection mask (default: mask.zarr beside the detections)")
    s.add_argument(
        "--ignore-flagged",
        dest="ignore_flagged",
        action="store_true",
        help="leave out detections flagged as azimuth ambiguities (ambiguity_of) that match no "
        "truth ship, as detections on difficult ships are (n_flagged_ignored)",
    )
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_evaluate)


def _parser_detectors(sub) -> None:
    """``sarship detectors``'s options."""
    s = sub.add_parser("detectors", help="list detectors with their parameters")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_detectors)


def _parser_demo(sub) -> None:
    """``sarship demo``'s options."""
    s = sub.add_parser(
        "demo", help="the main job on an embedded default: simulate, detect on a local Dask cluster, score"
    )
    s.add_argument("--out", default="sarship-demo")
    s.add_argument("--shape", type=_shape, default=(4096, 4096))
    s.add_argument("--ships", type=int, default=40)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--looks", type=float, default=4.0)
    s.add_argument("--scr-db", dest="scr_db", type=float, default=15.0)
    s.add_argument("--spacing", type=float, default=3.0, help="pixel spacing in metres (default 3)")
    s.add_argument(
        "--detector",
        default="os_cfar",
        help="default os_cfar: robust to the K-distributed sea (ca_cfar over-alarms there)",
    )
    s.add_argument("--set", action="append", metavar="KEY=VALUE")
    s.add_argument("--tile", type=_positive_int, default=1024)
    s.add_argument("--scheduler")
    s.add_argument(
        "--overwrite",
        action="store_true",
        help="write into an existing non-empty --out folder, replacing the demo's outputs",
    )
    s.set_defaults(func=cmd_demo)


#: Commands whose outputs are written aside and renamed into place: SIGTERM unwinds them.
WRITERS = ("simulate", "ingest", "detect", "demo", "enhance", "export")


def _exit_on_sigterm(command: str) -> None:
    """SIGTERM raises ``SystemExit(143)`` in the main thread, so that ``finally`` blocks and
    the atomic stores' clean-up run (the default action would end the process at once)."""
    import signal

    def stop(signum, frame):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM ends it at once
        print(f"sarship {command}: terminated", file=sys.stderr)
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


#: Batch commands that end their process with ``os._exit`` once their outputs are in place.
FAST_EXIT = ("simulate", "ingest", "detect", "evaluate", "detectors", "demo", "enhance", "export")


def console() -> None:
    """The ``sarship`` console script (and ``python -m sarship``): :func:`main`, then, for a batch
    command that returned, ``os._exit`` with its code after flushing stdout and stderr.

    The outputs are complete and renamed into place when ``main`` returns (a local Dask cluster
    is closed inside it); what ``os._exit`` skips is the interpreter's teardown (collecting
    every module of NumPy, SciPy, Numba, Dask and Zarr, joining idle executor threads):
    0.1-0.3 s of every command on a 2-core machine (issue 17). ``SARSHIP_FAST_EXIT=0`` restores
    the normal exit (e.g. under a coverage tool that writes at exit). Errors (``SystemExit``
    from ``main``) exit the normal way."""
    argv = sys.argv[1:]
    code = main(argv)
    command = next((x for x in argv if not x.startswith("-")), None)
    if command in FAST_EXIT and env_settings.read("fast_exit"):
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code if isinstance(code, int) else 0)
    raise SystemExit(code)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    if a.command in WRITERS:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            handler = signal.getsignal(signal.SIGTERM)
            temps = temporaries(a)
            existing = present(temps)
            _exit_on_sigterm(a.command)
            try:
                return _main(a)
            except SystemExit as exc:
                if exc.code == 128 + signal.SIGTERM:
                    # writes still in flight when the signal unwound the command (Zarr's I/O
                    # thread, a Dask task) may have re-created a temporary output after its
                    # removal: let them end, then remove what this run left
                    _drain_zarr()
                    remove_new(temps, existing)
                raise
            finally:  # (main called in-process, e.g. by tests: the caller's handler again)
                signal.signal(signal.SIGTERM, handler)
    return _main(a)


def _drain_zarr(timeout: float = 10.0) -> None:
    """Wait (at most ``timeout``) for the tasks still running on Zarr's I/O event loop."""
    import asyncio

    try:
        from zarr.core import sync as zsync
    except ImportError:
        return
    loop = (getattr(zsync, "loop", None) or [None])[0]
    if loop is None or not loop.is_running():
        return

    async def drain() -> None:
        me = asyncio.current_task()
        tasks = [t for t in asyncio.all_tasks() if t is not me]
        if tasks:
            await asyncio.wait(tasks, timeout=timeout)

    with contextlib.suppress(Exception):
        asyncio.run_coroutine_threadsafe(drain(), loop).result(timeout + 5)


def _main(a) -> int:
    # readers report problems themselves, as one line; keep libraries' log chatter off stderr
    import logging

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    try:
        return int(a.func(a) or 0)
    except InputError as exc:
        print(f"sarship {a.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sarship {a.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `sarship detectors | head`: the reader left; nothing to report
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            return _internal(a, exc)
        print(
            f"sarship {a.command}: error: no space to write ({_storage_text(exc)}); nothing was left "
            "behind: free space and run it again",
            file=sys.stderr,
        )
        return 3
    except Exception as exc:  # unexpected: one line unless debugging
        return _internal(a, exc)


def _internal(a, exc: BaseException) -> int:
    if env_settings.read("debug"):
        raise exc
    msg = str(exc).splitlines()[0] if str(exc) else ""
    print(
        f"sarship {a.command}: internal error: {type(exc).__name__}: {msg} (set SARSHIP_DEBUG=1 for the traceback)",
        file=sys.stderr,
    )
    return 1


def _storage_text(exc: OSError) -> str:
    return " ".join(str(exc).split()) or os.strerror(exc.errno)


if __name__ == "__main__":
    sys.exit(main())
