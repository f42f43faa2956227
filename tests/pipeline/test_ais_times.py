"""AIS timestamps (pipeline/ais/times.py): parsed as the standard library parses them, and the
string test of the time window exact to the second (it never drops a row inside the window)."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import pytest

from sarship.pipeline.ais.csv_formats import clock_times
from sarship.pipeline.ais.times import DayCache, TimeGate, parse_time

RNG_SEED = 20260


def _random_times(n: int, rng: np.random.Generator) -> np.ndarray:
    lo = datetime(2000, 1, 2, tzinfo=UTC).timestamp()
    hi = datetime(2090, 1, 1, tzinfo=UTC).timestamp()
    return np.round(rng.uniform(lo, hi, n), 3)


def test_parse_time_agrees_with_datetime_on_every_form():
    rng = np.random.default_rng(RNG_SEED)
    days = DayCache()
    for t in _random_times(400, rng).tolist():
        dt = datetime.fromtimestamp(t, UTC)
        whole = dt.replace(microsecond=0)
        zone = timezone(timedelta(minutes=int(rng.integers(-12 * 4, 14 * 4)) * 15))
        local = dt.astimezone(zone)
        forms = {
            whole.strftime("%Y-%m-%dT%H:%M:%S"): whole.timestamp(),
            whole.strftime("%Y-%m-%d %H:%M:%SZ"): whole.timestamp(),
            whole.strftime("%d/%m/%Y %H:%M:%S"): whole.timestamp(),
            dt.strftime("%Y-%m-%dT%H:%M:%S.%f"): dt.timestamp(),
            local.isoformat(): t,
            local.strftime("%Y-%m-%dT%H:%M:%S.%f%z"): t,
            f"{t:.3f}": t,
            str(round(t * 1000)): round(t * 1000) / 1000,
        }
        for text, want in forms.items():
            assert parse_time(text.encode(), days) == pytest.approx(want, abs=1e-6), text


@pytest.mark.parametrize(
    "text",
    ["", "abc", "2023-13-01T00:00:00", "31/02/2023 00:00:00", "2023-01-01T24:00:00", "2023-01-01T10:61:00", "12", "-5"],
)
def test_parse_time_gives_nan_for_what_is_no_time(text):
    assert math.isnan(parse_time(text.encode(), DayCache()))


def test_clock_times_vectorised_agrees_with_parse_time():
    rng = np.random.default_rng(RNG_SEED + 1)
    days = DayCache()
    stamps = [datetime.fromtimestamp(t, UTC).strftime("%d/%m/%Y %H:%M:%S").encode() for t in _random_times(300, rng)]
    stamps += [b"2023-02-27T10:00:00", b"2023-02-27 25:00:00", b"garbage-is-19-bytes", b"31/02/2023 10:00:00"]
    got = clock_times(stamps, days)
    want = np.array([parse_time(s, days) for s in stamps])
    np.testing.assert_array_equal(got, want)
    assert np.isnan(want[-3:]).all() and np.isfinite(want[:-3]).all()


@pytest.mark.parametrize("form", ["%d/%m/%Y %H:%M:%S", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d %H:%M:%S"])
def test_the_time_gate_passes_exactly_the_seconds_of_the_window(form):
    rng = np.random.default_rng(RNG_SEED + 2)
    days = DayCache()
    for _ in range(20):
        t0 = float(rng.uniform(1.6e9, 1.7e9))
        t1 = t0 + float(rng.choice([0.5, 600.0, 3600.0, 86_400.0, 200_000.0]))
        gate = TimeGate(t0, t1, days)
        ts = np.floor(rng.uniform(t0 - 2 * 86_400, t1 + 2 * 86_400, 300))
        ts = np.concatenate([ts, np.floor([t0 - 1, t0, t0 + 1, t1 - 1, t1, t1 + 1])])
        for t in ts.tolist():
            text = datetime.fromtimestamp(t, UTC).strftime(form).encode()
            lo, hi = gate.bounds(text[:10])
            passed = lo <= text[11:19] <= hi
            assert passed == (math.floor(t0) <= t <= math.floor(t1)), (text, t0, t1)
            assert gate.may_pass(text) == passed
            assert gate.may_pass(b"%.3f" % t) == (t0 - 1 <= t <= t1 + 1)


def test_the_time_gate_lets_through_what_it_cannot_read():
    gate = TimeGate(1.6e9, 1.6e9 + 3600, DayCache())
    for text in (b"garbage", b"2020-09-13T12:26:40+05:00", b"99/99/9999 00:00:00"):
        assert gate.may_pass(text)
