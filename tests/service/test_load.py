"""No job lost under concurrent submission and polling, against a real ``sarship serve``: the
small, timing-free version of ``bench/bench_service_load.py`` (which reports the rates)."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

httpx = pytest.importorskip("httpx")
from svc import Server, data_with_scene, free_port  # noqa: E402

N_JOBS = 20


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = data_with_scene(tmp_path_factory.mktemp("load"), shape=(128, 128), seed=4, n=4)  # one tile
    srv = Server(data, free_port(), SARSHIP_CONCURRENCY="2").start()
    yield srv
    srv.stop()


def test_concurrent_jobs_none_lost(server):
    u = server.url
    body = {"inputs": {"scene": "s1", "guard": 11, "background": 31, "min_area_px": 1}}
    ids: list[str] = []
    bad: list[str] = []
    done = threading.Event()

    def submit(_: int) -> None:
        r = httpx.post(u + "/processes/ca_cfar/execution", json=body, timeout=60)
        if r.status_code != 201:
            bad.append(f"POST {r.status_code} {r.text}")
        else:
            ids.append(r.json()["jobID"])

    def poll() -> None:
        with httpx.Client(timeout=60) as c:
            k = 0
            while not done.is_set() and k < 5000:
                if not ids:
                    time.sleep(0.01)
                    continue
                r = c.get(f"{u}/jobs/{ids[k % len(ids)]}")
                if r.status_code != 200 or r.json()["status"] not in ("accepted", "running", "successful"):
                    bad.append(f"GET {r.status_code} {r.text}")
                k += 1

    pollers = [threading.Thread(target=poll) for _ in range(2)]
    for p in pollers:
        p.start()
    try:
        with ThreadPoolExecutor(8) as pool:
            list(pool.map(submit, range(N_JOBS)))
        t_end = time.time() + 120
        while time.time() < t_end:
            listed = httpx.get(u + "/jobs", params={"limit": 10000}).json()["jobs"]
            if all(j["status"] == "successful" for j in listed if j["jobID"] in ids) and len(listed) >= N_JOBS:
                break
            time.sleep(0.3)
    finally:
        done.set()
        for p in pollers:
            p.join()
    assert not bad, bad[:5]
    assert len(ids) == len(set(ids)) == N_JOBS
    listed = httpx.get(u + "/jobs", params={"limit": 10000}).json()["jobs"]
    assert sorted(j["jobID"] for j in listed) == sorted(ids)  # each exactly once, nothing else
    for j in listed:
        assert j["status"] == "successful" and j["attempts"] == 1 and j["progress"] == 100, j
