"""The web page (``/ui/``) end to end: a real ``sarship serve`` (uvicorn, local Dask cluster,
SQLite store) with API tokens, driven in Debian's headless Chromium through Playwright.

In the browser: enter the token, fill the form built from the process schemas, submit, see the
job go live to ``successful`` in the list, open it by keyboard, see every detection listed and
drawn as a box on the map of the job's quicklook tiles (tile PNGs answered 200), pick one in the
table (the tiles' red mask pixels lie under its box); a bad parameter shows the API's problem
detail beside the form, as text; a running job is dismissed from the list in a narrow window; the
ingest panel follows passes dropped in the inbox (one ingested, one quarantined with its reason)
and the new scene joins the form; a scene file uploaded from the page (refused without a token,
with the API's detail shown) is ingested and chosen in the form, and a detection runs on it; a
file that cannot be ingested shows why; a job on a scene with ground truth shows its scores; a
job whose detections carry AIS results colours them matched / dark / none, names the vessels
and draws a legend and the unmatched AIS vessels; the
API docs (``/docs``, Swagger UI) render with the browser limited to the server. The page must
raise no JavaScript error and log no console error.
Without a browser: the page's cache headers and the landing page's HTML redirect.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
Image = pytest.importorskip("PIL.Image")
from conftest import blobs_scene, write_scene  # noqa: E402
from svc import Server, free_port, wait_job  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
TOKEN = "web-test-token"
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
TILE_RE = re.compile(r"/jobs/[0-9a-f]+/tiles/\d+/\d+/\d+\.png$")
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("web") / "data"
    (data / "scenes").mkdir(parents=True)
    # wider than tall, 2 rows x 3 columns of map tiles at full resolution: rows and columns cannot be
    # mixed up unseen
    write_scene(
        data / "scenes" / "s1.zarr",
        {"intensity": blobs_scene((300, 600), looks=2.0, seed=3, n=24)},
        tile=128,
        looks=2.0,
    )
    # small tiles: a job of many short tasks, so a dismissed job does not hold the workers long
    write_scene(
        data / "scenes" / "small_tiles.zarr",
        {"intensity": blobs_scene((300, 260), looks=2.0, seed=4)},
        tile=32,
        looks=2.0,
    )
    inbox = data.parent / "inbox"
    inbox.mkdir()
    srv = Server(
        data, free_port(), SARSHIP_TOKENS=f'["{TOKEN}"]', SARSHIP_INBOX=str(inbox), SARSHIP_INBOX_INTERVAL_S="600"
    ).start()
    srv.inbox = inbox
    yield srv
    srv.stop()


class Watched:
    """A page whose JavaScript errors, console errors and HTTP answers are recorded."""

    def __init__(self, page):
        self.page = page
        self.errors: list[str] = []
        self.responses: list[tuple[str, int]] = []
        #: (status, URL) of the bad requests a test makes on purpose (the browser logs them as errors)
        self.expected: set[tuple[int, str]] = set()
        page.on("pageerror", lambda exc: self.errors.append(f"page error: {exc}"))
        page.on("console", self._console)
        page.on("response", lambda r: self.responses.append((r.url, r.status)))

    def _console(self, msg) -> None:
        if msg.type not in ("error", "warning"):
            return
        url = (msg.location or {}).get("url", "")
        if msg.type == "error" and any(f"status of {st} " in msg.text and url == u for st, u in self.expected):
            return
        self.errors.append(f"console {msg.type}: {msg.text} ({url})")


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent (Debian's chromium package drives these tests)")
    profile = tmp_path_factory.mktemp("chromium-profile")
    with sync_api.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            str(profile),
            executable_path=str(CHROMIUM),
            headless=True,
            args=ARGS,
            viewport={"width": 1280, "height": 900},
        )
        ctx.set_default_timeout(20_000)
        yield ctx
        ctx.close()


@pytest.fixture
def page(browser, server):
    pg = browser.new_page()
    w = Watched(pg)
    yield w
    pg.close()
    assert not w.errors, w.errors


def open_ui(w: Watched, url: str) -> None:
    w.page.goto(url + "/ui/")
    w.page.wait_for_selector("body[data-ready=true]")
    w.page.wait_for_selector("#param-pfa")


def set_token(w: Watched) -> None:
    pg = w.page
    pg.click("details.token summary")
    pg.fill("#token", TOKEN)
    pg.click("#token-form button[type=submit]")
    assert "token is set" in pg.inner_text("#token-state")


def job_ids(url: str) -> list[str]:
    return [j["jobID"] for j in httpx.get(url + "/jobs").json()["jobs"]]


def test_submit_see_it_finish_and_its_detections(server, page, tmp_path):
    u, pg = server.url, page.page
    open_ui(page, u)
    assert pg.get_attribute("#dashboard-link", "href") == "../dashboard"
    assert httpx.get(u + "/dashboard").status_code == 307  # the page's link leads to the Dask dashboard
    ing = httpx.get(u + "/ingest")
    if ing.status_code == 404 or not ing.json()["enabled"]:
        pg.wait_for_selector("#ingest-state:has-text('not configured')")
    else:
        pg.wait_for_selector("#ingest-state:has-text('enabled')")
    # the form is generated from the schemas: ranges and defaults of ca_cfar's inputs
    desc = httpx.get(u + "/processes/ca_cfar").json()["inputs"]
    assert pg.get_attribute("#param-guard", "min") == str(desc["guard"]["schema"]["minimum"])
    assert pg.input_value("#param-guard") == str(desc["guard"]["schema"]["default"])
    assert pg.input_value("#param-device") == "auto"
    assert pg.locator("label[for=param-guard]").count() == 1
    # the upload form comes first, in view without scrolling; the detector's few main parameters
    # are open and the rest (about twenty) wait in a closed "Advanced parameters" section
    view_h = pg.viewport_size["height"]
    up, adv = pg.locator("#upload-btn").bounding_box(), pg.locator("#advanced").bounding_box()
    assert up["y"] + up["height"] <= view_h and up["y"] < adv["y"], (up, adv)
    assert pg.locator("#advanced").get_attribute("open") is None
    assert pg.locator("#param-pfa").is_visible() and pg.locator("#param-background").is_visible()
    assert pg.locator("#param-min_area_px").is_hidden() and pg.locator("#param-land_mask").is_hidden()
    n_adv = pg.locator("#advanced [data-param]").count()
    assert n_adv >= 15 and pg.locator("#params [data-param]").count() == len(desc) - 1  # all but the scene
    assert f"({n_adv})" in pg.inner_text("#advanced summary")

    pg.select_option("#scene-select", "s1")
    pg.select_option("#process", "ca_cfar")
    pg.fill("#param-guard", "11")
    pg.fill("#param-background", "31")
    pg.click("#advanced summary")
    assert pg.locator("#param-min_area_px").is_visible()
    pg.fill("#param-min_area_px", "1")
    before = set(job_ids(u))
    page.expected.add((401, u + "/processes/ca_cfar/execution"))
    pg.click("#submit-btn")  # no token yet: POST needs one
    pg.wait_for_selector("#submit-error:not([hidden])")
    assert "401" in pg.inner_text("#submit-error") and "Bearer" in pg.inner_text("#submit-error")
    assert set(job_ids(u)) == before

    set_token(page)
    pg.click("#submit-btn")
    link = pg.wait_for_selector("#submit-ok a")
    job_id = link.inner_text()
    assert pg.locator("#submit-error").is_hidden()
    # the job appears in the list and goes live to successful
    row = f"#jobs-table tr[data-job-id='{job_id}']"
    pg.wait_for_selector(row)
    pg.wait_for_selector(f"{row}[data-status=successful]", timeout=60_000)
    assert pg.inner_text(f"{row} .c-status") == "successful" and "100%" in pg.inner_text(f"{row} .c-prog")
    assert httpx.get(f"{u}/jobs/{job_id}").json()["status"] == "successful"

    # open it with the keyboard
    pg.focus(f"{row} a.job-link")
    pg.keyboard.press("Enter")
    pg.wait_for_selector("#map[data-ready=true]")
    fc = httpx.get(f"{u}/jobs/{job_id}/results/detections").json()
    n = len(fc["features"])
    assert n >= 5
    assert pg.locator("#det-table tbody tr").count() == n
    assert pg.locator("#map path.det-box").count() == n
    assert f"({n})" in pg.inner_text("#det-h")
    first = fc["features"][0]["properties"]
    assert pg.inner_text("#det-table tbody tr:first-child td:nth-child(4)") == str(first["area_px"])
    # the outputs are linked
    for key in httpx.get(f"{u}/jobs/{job_id}/results").json():
        assert pg.locator("#job-result ul.links a", has_text=key).count() >= 1, key
    # quicklook tiles: loaded with 200, none failed
    pg.wait_for_selector("#map img.leaflet-tile-loaded")
    tiles = [(url, st) for url, st in page.responses if TILE_RE.search(url)]
    assert tiles and all(st == 200 for _, st in tiles), tiles

    # choosing a detection in the table selects its box and zooms the map in on it; the tiles
    # there show its mask pixels in red right under the box (tiles and boxes line up)
    zoom0 = float(pg.get_attribute("#map", "data-zoom"))
    # the largest ship in the top row of tiles, right of the first column (tile x > y)
    big = max(
        (
            i
            for i in range(n)
            if fc["features"][i]["properties"]["centroid_px"][1] > 300
            and fc["features"][i]["properties"]["centroid_px"][0] < 250
        ),
        key=lambda i: fc["features"][i]["properties"]["area_px"],
    )
    pg.click(f"#det-table tbody tr:nth-child({big + 1}) button.det-go")
    pg.wait_for_selector(f"#det-table tbody tr.selected[aria-current=true][data-det='{big}']")
    box = pg.locator("#map path.det-box[stroke='#00e5ff']")
    assert box.count() == 1
    pg.wait_for_function("z => Number(document.querySelector('#map').dataset.zoom) > z", arg=zoom0)
    pg.wait_for_function(
        "() => !document.querySelector('#map .leaflet-zoom-anim') && "
        "[...document.querySelectorAll('#map img.leaflet-tile')].every(t => "
        "t.classList.contains('leaflet-tile-loaded'))"
    )
    pg.wait_for_timeout(300)  # the tiles' fade-in
    b, m = box.bounding_box(), pg.locator("#map").bounding_box()
    shot = Image.open(io.BytesIO(pg.locator("#map").screenshot())).convert("RGB")
    sx, sy = shot.width / m["width"], shot.height / m["height"]
    cx, cy = b["x"] + b["width"] / 2 - m["x"], b["y"] + b["height"] / 2 - m["y"]
    r, g, bl = shot.getpixel((int(cx * sx), int(cy * sy)))
    assert r > 150 and r > g + 60 and r > bl + 60, (r, g, bl)
    pg.screenshot(path=str(tmp_path / "job.png"), full_page=True)


def test_bad_parameter_shows_the_problem(server, page):
    u, pg = server.url, page.page
    open_ui(page, u)
    set_token(page)
    pg.select_option("#scene-select", "s1")
    pg.fill("#param-guard", "10")  # an integer in range, but windows are odd: only the API knows
    before = set(job_ids(u))
    page.expected.add((400, u + "/processes/ca_cfar/execution"))
    pg.click("#submit-btn")
    pg.wait_for_selector("#submit-error:not([hidden])")
    api = httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1", "guard": 10}}, headers=AUTH)
    assert api.status_code == 400
    shown = pg.inner_text("#submit-error")
    assert api.json()["detail"] in shown and "400" in shown
    assert pg.get_attribute("#param-guard", "aria-invalid") == "true"
    assert set(job_ids(u)) == before
    # an advanced parameter the API refuses: its closed section opens on it
    pg.fill("#param-guard", "41")
    pg.click("#advanced summary")
    pg.fill("#param-land_window", "16")  # in range, but even
    pg.click("#advanced summary")
    assert pg.locator("#param-land_window").is_hidden()
    pg.click("#submit-btn")
    pg.wait_for_function("() => document.querySelector('#submit-error').innerText.includes('land_window')")
    assert (
        pg.get_attribute("#param-land_window", "aria-invalid") == "true"
        and pg.locator("#param-land_window").is_visible()
    )
    pg.fill("#param-land_window", "15")
    # a scene outside the allowed folders: the API's detail again
    pg.fill("#param-guard", "41")
    pg.fill("#scene-path", "/etc")
    pg.click("#submit-btn")
    pg.wait_for_function("() => document.querySelector('#submit-error').innerText.includes('outside')")
    assert pg.get_attribute("#scene-path", "aria-invalid") == "true"
    # text from the API is text: markup echoed in a problem detail is shown, not parsed
    pg.fill("#scene-path", "<b id=injected>x</b>")
    pg.click("#submit-btn")
    pg.wait_for_function("() => document.querySelector('#submit-error').innerText.includes('<b id=injected>')")
    assert pg.locator("#injected").count() == 0


def test_dismiss_a_running_job_from_the_list_in_a_narrow_window(server, page, tmp_path):
    u, pg = server.url, page.page
    pg.set_viewport_size({"width": 380, "height": 800})
    open_ui(page, u)
    set_token(page)
    # the page fits the narrow window (tables scroll inside their own box)
    assert pg.evaluate("() => document.documentElement.scrollWidth <= window.innerWidth + 1")
    pg.select_option("#scene-select", "small_tiles")
    pg.select_option("#process", "lmm")  # per-pixel mixture fits: a few seconds for this scene
    pg.wait_for_selector("#params legend:has-text('lmm')")
    assert pg.input_value("#param-method") == "grid"  # a choice from the schema's pattern
    pg.click("#submit-btn")
    job_id = pg.wait_for_selector("#submit-ok a").inner_text()
    row = f"#jobs-table tr[data-job-id='{job_id}']"
    pg.wait_for_selector(f"{row} button:has-text('Dismiss')")
    assert pg.locator("#jobs-table tbody tr").first.get_attribute("data-job-id") == job_id  # newest first
    pg.click(f"{row} button:has-text('Dismiss')")
    pg.wait_for_selector(f"{row}[data-status=dismissed]")
    assert pg.locator(f"{row} button").count() == 0
    assert wait_job(u, job_id)["status"] == "dismissed"
    pg.screenshot(path=str(tmp_path / "narrow.png"), full_page=True)


def test_ingest_panel_follows_the_inbox(server, page, tmp_path):
    """Two passes land in the inbox (complete: ``.done`` markers); "Scan now" finds them
    before the scheduled scan (600 s away); the panel shows one ingested and one quarantined
    with the reason, and the new scene joins the form's scene list."""
    u, pg = server.url, page.page
    np.save(server.inbox / "pass1.npy", blobs_scene((200, 180), looks=2.0, seed=11))
    (server.inbox / "pass1.npy.done").touch()
    (server.inbox / "broken.npy").write_bytes(b"this is not a numpy file")
    (server.inbox / "broken.npy.done").touch()
    open_ui(page, u)
    set_token(page)
    pg.wait_for_selector("#ingest-state:has-text('enabled')")
    assert str(server.inbox) in pg.inner_text("#ingest-info")
    pg.click("#ingest-scan")
    pg.wait_for_selector("#ingest-scan-msg:has-text('scan requested')")
    good = pg.wait_for_selector("#ingest-table tr[data-status=ingested]:has-text('pass1.npy')", timeout=60_000)
    bad = pg.wait_for_selector("#ingest-table tr[data-status=quarantined]:has-text('broken.npy')", timeout=60_000)
    passes = {p["file"].rsplit("/", 1)[-1]: p for p in httpx.get(u + "/ingest").json()["passes"]}
    assert passes["broken.npy"]["reason"] and passes["broken.npy"]["reason"] in bad.inner_text()
    scene = passes["pass1.npy"]["sceneID"]
    assert scene and scene in good.inner_text()
    # the ingested scene joins the form's list once its ingest job has finished
    pg.wait_for_selector(f"#scene-select option[value='{scene}']:not([disabled])", state="attached", timeout=30_000)
    assert pg.inner_text("#ingest-backlog") == "0"
    pg.screenshot(path=str(tmp_path / "ingest.png"), full_page=True)


def test_page_caching_and_landing_redirect(server):
    u = server.url
    page = httpx.get(u + "/ui/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert page.headers["cache-control"] == "no-cache"
    assert httpx.get(u + "/ui/", headers={"If-None-Match": page.headers["etag"]}).status_code == 304
    assets = re.findall(r'(?:src|href)="(static/[^"]+\?v=[0-9a-f]+)"', page.text)
    assert len(assets) == 4, assets  # app.js, app.css, leaflet.js, leaflet.css: all served here, no CDN
    links = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert not [x for x in links if "//" in x], links  # nothing from elsewhere
    for a in assets:
        r = httpx.get(f"{u}/ui/{a}")
        assert r.status_code == 200 and "immutable" in r.headers["cache-control"], (a, r.headers)
    stale = httpx.get(f"{u}/ui/static/app.js?v=old")
    assert stale.status_code == 200 and stale.headers["cache-control"] == "no-cache"
    for bad in ("/ui/static/nope.js", "/ui/static/../web.py", "/ui/static/%2e%2e/web.py"):
        r = httpx.get(u + bad)
        assert r.status_code == 404 and r.json()["title"], bad
    assert httpx.get(u + "/ui").headers["location"].endswith("/ui/")
    # browsers asking for HTML land on the page; JSON clients keep the landing document
    html = httpx.get(u + "/", headers={"Accept": "text/html,application/xhtml+xml,*/*;q=0.8"})
    assert html.status_code == 303 and html.headers["location"].endswith("/ui/")
    forced = httpx.get(u + "/?f=json", headers={"Accept": "text/html"})
    assert forced.status_code == 200 and forced.json()["title"] == "sarship"
    land = httpx.get(u + "/").json()
    assert any(
        x["rel"] == "alternate" and x["type"] == "text/html" and x["href"].endswith("/ui/") for x in land["links"]
    )
    assert httpx.get(u + "/", headers={"Accept": "application/json"}).status_code == 200


def test_api_docs_render_offline(server, page):
    """``/docs`` (Swagger UI) renders the operations with the browser limited to the server:
    its script and style sheet are the vendored swagger-ui-dist, not a CDN's."""
    u, pg = server.url, page.page
    elsewhere: list[str] = []

    def only_here(route):
        if route.request.url.startswith(u + "/") or route.request.url.startswith("data:"):
            route.continue_()
        else:
            elsewhere.append(route.request.url)
            route.abort()

    pg.route("**/*", only_here)
    pg.goto(u + "/docs")
    pg.wait_for_selector(".opblock-summary-path:has-text('/processes')")
    assert pg.locator(".opblock").count() >= 10
    assert pg.locator(".swagger-ui .info .title:has-text('sarship')").count() == 1
    assert not elsewhere, elsewhere
    assert [url for url, _ in page.responses if "/ui/static/vendor/swagger-ui/swagger-ui-bundle.js" in url]
    assert httpx.get(u + "/redoc").status_code == 404  # ReDoc (CDN only) is off


def test_upload_a_scene_then_detect_on_it(server, page, tmp_path):
    u, pg = server.url, page.page
    f = tmp_path / "upload-me.npy"
    np.save(f, blobs_scene((200, 240), looks=2.0, seed=21, n=10))
    open_ui(page, u)
    pg.evaluate("() => window.localStorage.removeItem('sarship.token')")  # earlier tests saved one
    pg.reload()
    pg.wait_for_selector("body[data-ready=true]")
    # without a token the API refuses the upload: its problem detail is shown
    page.expected.add((401, u + "/scenes?filename=upload-me.npy"))
    pg.set_input_files("#upload-file", str(f))
    pg.click("#upload-btn")
    pg.wait_for_selector("#upload-error:not([hidden])")
    assert "401" in pg.inner_text("#upload-error") and "Bearer" in pg.inner_text("#upload-error")

    set_token(page)
    pg.set_input_files("#upload-file", str(f))
    pg.click("#upload-btn")
    pg.wait_for_selector("#upload-state[data-scene]", timeout=90_000)
    assert pg.locator("#upload-error").is_hidden()
    scene = pg.get_attribute("#upload-state", "data-scene")
    assert scene in pg.inner_text("#upload-state") and "ready" in pg.inner_text("#upload-state")
    assert httpx.get(f"{u}/scenes/{scene}").json()["status"] == "ready"
    # the new scene is listed and chosen in the form: submit a detection on it
    assert pg.locator(f"#scene-select option[value='{scene}']:not([disabled])").count() == 1
    assert pg.input_value("#scene-select") == scene
    # listed by what the person uploaded, not by the hash alone
    assert "upload-me" in pg.inner_text(f"#scene-select option[value='{scene}']")
    pg.select_option("#process", "ca_cfar")
    pg.fill("#param-guard", "11")
    pg.fill("#param-background", "31")
    pg.click("#advanced summary")
    pg.fill("#param-min_area_px", "1")
    pg.click("#submit-btn")
    job_id = pg.wait_for_selector("#submit-ok a").inner_text()
    st = wait_job(u, job_id)
    assert st["status"] == "successful", st
    assert httpx.get(f"{u}/jobs/{job_id}/results/metrics").json()["scene"]["path"].endswith(f"{scene}.zarr")


def test_upload_of_a_bad_file_shows_why(server, page, tmp_path):
    u, pg = server.url, page.page
    f = tmp_path / "broken.npy"
    f.write_bytes(b"not a numpy file at all")
    open_ui(page, u)
    set_token(page)
    pg.set_input_files("#upload-file", str(f))
    pg.click("#upload-btn")
    pg.wait_for_selector("#upload-error:not([hidden])", timeout=90_000)
    assert "ingest failed" in pg.inner_text("#upload-error")
    assert pg.locator("#upload-state[data-scene]").count() == 0


def test_job_view_shows_scores_and_lonlat_of_a_georeferenced_scene(server, page, tmp_path):
    """A job on a scene with ground truth shows its scores; the scene is georeferenced, so its
    map is in lon/lat: Web Mercator, graticule labelled in degrees around the scene's position,
    quicklook tiles warped into place, detections drawn from their WGS84 outlines and listed by
    lat/lon, the pointer's lon/lat. A scene without georeference keeps its pixel grid."""
    from sarship.cli import main

    u, pg = server.url, page.page
    scene = server.data / "scenes" / "truthy.zarr"
    if not scene.exists():  # `sarship simulate`, in this process (a process start-up costs seconds)
        assert (
            main(["simulate", str(scene), "--shape", "512x512", "--ships", "5", "--seed", "2", "--geo", "10.5,55.2"])
            == 0
        )
    assert Path(f"{scene}.truth.geojson").is_file()
    r = httpx.post(u + "/processes/os_cfar/execution", json={"inputs": {"scene": "truthy"}}, headers=AUTH)
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    assert wait_job(u, job_id)["status"] == "successful"
    scores = httpx.get(f"{u}/jobs/{job_id}/results/metrics").json()["scores"]
    pg.goto(f"{u}/ui/#/jobs/{job_id}")
    pg.wait_for_selector("#scores")
    shown = {
        pg.locator("#scores dt").nth(i).inner_text(): pg.locator("#scores dd").nth(i).inner_text()
        for i in range(pg.locator("#scores dt").count())
    }
    assert shown["n_truth"] == "5" == str(scores["n_truth"])
    for k in ("pd", "precision"):
        assert k in shown and abs(float(shown[k]) - scores[k]) < 1e-3, (k, shown, scores)

    grid = httpx.get(f"{u}/jobs/{job_id}/tiles.json").json()["lonlat"]
    lon = np.array(grid["lon"])
    lat = np.array(grid["lat"])
    pg.wait_for_selector("#map[data-ready=true][data-crs='EPSG:3857']")
    pg.wait_for_selector("#map img.warp-tile.loaded")
    tiles = [(url, st) for url, st in page.responses if TILE_RE.search(url) and job_id in url]
    assert tiles and all(st == 200 for _, st in tiles), tiles
    # graticule: degree labels on both edges, their values around the scene's extent
    lons = [float(x) for x in pg.eval_on_selector_all(".grat-lon", "els => els.map(e => e.dataset.lon)")]
    lats = [float(x) for x in pg.eval_on_selector_all(".grat-lat", "els => els.map(e => e.dataset.lat)")]
    assert len(lons) >= 2 and len(lats) >= 2, (lons, lats)
    assert all(t.endswith("° E") for t in pg.locator(".grat-lon").all_inner_texts())
    assert all(t.endswith("° N") for t in pg.locator(".grat-lat").all_inner_texts())
    span_lon, span_lat = lon.max() - lon.min(), lat.max() - lat.min()
    assert lon.min() - span_lon < min(lons) and max(lons) < lon.max() + span_lon, (lons, lon.min(), lon.max())
    assert lat.min() - span_lat < min(lats) and max(lats) < lat.max() + span_lat, (lats, lat.min(), lat.max())
    # detections: drawn from their WGS84 outlines, listed by lat/lon
    fc = httpx.get(f"{u}/jobs/{job_id}/results/detections").json()
    assert pg.locator("#map path.det-box").count() == len(fc["features"]) >= 1
    clon, clat = fc["features"][0]["properties"]["centroid_lonlat"]
    assert pg.inner_text("#det-table tbody tr:first-child td:nth-child(2)") == f"{clat:.5f}° N, {clon:.5f}° E"
    # the pointer in the middle of the scene reads the scene centre's lon/lat
    pg.locator("#map").scroll_into_view_if_needed()
    m = pg.locator("#map").bounding_box()
    ctr = pg.evaluate(
        "() => { const c = document.querySelector('#map .scene-outline').getBoundingClientRect(); "
        "return [c.x + c.width / 2, c.y + c.height / 2]; }"
    )
    assert m["x"] < ctr[0] < m["x"] + m["width"] and m["y"] < ctr[1] < m["y"] + m["height"]
    pg.mouse.move(*ctr)
    pg.wait_for_function("() => document.querySelector('#map-cursor').textContent.includes('°')")
    got = re.fullmatch(r"([\d.]+)° N, ([\d.]+)° E", pg.inner_text("#map-cursor"))
    assert got, pg.inner_text("#map-cursor")
    n = len(grid["rows"]) // 2
    assert abs(float(got[1]) - lat[n, n]) < 0.1 * span_lat and abs(float(got[2]) - lon[n, n]) < 0.1 * span_lon
    pg.screenshot(path=str(tmp_path / "scores.png"), full_page=True)
    # a scene without truth: no scores on its job view
    r = httpx.post(u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "s1"}}, headers=AUTH)
    other = r.json()["jobID"]
    assert wait_job(u, other)["status"] == "successful"
    pg.goto(f"{u}/ui/#/jobs/{other}")
    pg.wait_for_selector("#map[data-ready=true]")
    assert "scores" not in httpx.get(f"{u}/jobs/{other}/results/metrics").json()
    assert pg.locator("#scores").count() == 0
    # no georeference: the scene's pixel grid, the pointer in rows and columns, no graticule
    assert "lonlat" not in httpx.get(f"{u}/jobs/{other}/tiles.json").json()
    assert pg.get_attribute("#map", "data-crs") == "pixels" and pg.locator(".grat-label").count() == 0
    pg.locator("#map").scroll_into_view_if_needed()
    m = pg.locator("#map").bounding_box()
    pg.mouse.move(m["x"] + m["width"] / 2, m["y"] + m["height"] / 2)
    pg.wait_for_function("() => /^row \\d+, col \\d+$/.test(document.querySelector('#map-cursor').textContent)")


def test_detections_coloured_by_ais_with_names_legend_and_unmatched_vessels(server, page, tmp_path):
    """A job given AIS (REST input ``ais``: a simulated georeferenced scene with moving ships and
    its AIS file in the scene folder): each box in its AIS state's colour (matched, dark, none),
    the vessel's name and MMSI in the table and the box's tooltip, a legend with the counts; the
    unmatched AIS vessels as markers from the results' ``ais_unmatched`` link."""
    import json

    from sarship.cli import main

    u, pg = server.url, page.page
    scene = server.data / "scenes" / "aisy.zarr"
    ais = server.data / "scenes" / "aisy.csv"  # inside the allowed folders
    if not scene.exists():
        args = ["simulate", str(scene), "--shape", "768x768", "--ships", "14", "--seed", "11", "--geo", "5.5,56.5"]
        assert main([*args, "--moving", "--ais", str(ais), "--dark-fraction", "0.3"]) == 0
    r = httpx.post(
        u + "/processes/ca_cfar/execution", json={"inputs": {"scene": "aisy", "ais": [str(ais)]}}, headers=AUTH
    )
    assert r.status_code == 201, r.text
    job_id = r.json()["jobID"]
    assert wait_job(u, job_id)["status"] == "successful"
    out = server.data / "jobs" / job_id
    assert "ais_unmatched" in httpx.get(f"{u}/jobs/{job_id}/results").json()
    feats = httpx.get(f"{u}/jobs/{job_id}/results/detections").json()["features"]
    unmatched = json.loads((out / "ais_unmatched.geojson").read_text())["features"]
    state = ["matched" if f["properties"]["ais"] else "dark" if f["properties"]["dark"] else "none" for f in feats]
    n = {k: state.count(k) for k in ("matched", "dark", "none")}
    assert n["matched"] >= 1 and n["dark"] >= 1 and unmatched, (n, len(unmatched))

    pg.goto(f"{u}/ui/#/jobs/{job_id}")
    pg.wait_for_selector("#map[data-ready=true][data-crs='EPSG:3857']")
    pg.wait_for_selector("#ais-legend")
    colours = {"matched": "#2ee06f", "dark": "#ff3b30", "none": "#ffd400"}
    for k, colour in colours.items():
        strokes = pg.eval_on_selector_all(f"#map path.det-{k}", "els => els.map(e => e.getAttribute('stroke'))")
        assert len(strokes) == n[k] and set(strokes) <= {colour}, (k, strokes)
        assert pg.inner_text(f"#ais-legend li[data-state={k}] b") == str(n[k])
    assert pg.inner_text("#ais-legend li[data-state=unmatched] b") == str(len(unmatched))
    assert pg.locator("#map path.ais-unmatched").count() == len(unmatched)
    # the table: the vessel's name and MMSI of each matched detection, "dark" for the dark ones
    assert pg.inner_text("#det-table thead tr th:last-child") == "AIS vessel"
    for i, f in enumerate(feats):
        row = pg.locator(f"#det-table tbody tr[data-det='{i}']")
        assert row.get_attribute("data-ais") == state[i]
        cell = row.locator("td:last-child").inner_text()
        a = f["properties"]["ais"]
        if a:
            assert f"MMSI {a['mmsi']}" in cell and (a["name"] or "unnamed").strip() in cell, (cell, a)
        elif state[i] == "dark":
            assert cell == "dark"
    # selecting a detection highlights it; selecting another gives the first its AIS colour back
    first, other = state.index("matched"), state.index("dark")
    pg.locator(f"#det-table tbody tr[data-det='{first}'] td:nth-child(2)").click()
    sel = f"#map path.det-box[data-det='{first}']"
    assert pg.locator(sel).get_attribute("stroke") == "#00e5ff"
    pg.locator(f"#det-table tbody tr[data-det='{other}'] td:nth-child(2)").click()
    assert pg.locator(sel).get_attribute("stroke") == colours["matched"]
    # the tooltip of a matched box names its vessel
    name = feats[first]["properties"]["ais"]["mmsi"]
    pg.locator(sel).dispatch_event("mouseover")
    pg.wait_for_selector(".leaflet-tooltip")
    assert f"MMSI {name}" in pg.inner_text(".leaflet-tooltip")
    pg.screenshot(path=str(tmp_path / "ais.png"), full_page=True)
