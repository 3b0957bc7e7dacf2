"""The poll cache (service/api/poll_cache.py): answers at most ttl old, one read shared by
concurrent misses, metrics answers tied to the job view they were computed under, own writes
dropping entries at once, errors never cached. A fake clock keeps every case deterministic; reads
run in the real threadpool."""

import asyncio
import threading

import pytest

from service.api.poll_cache import PollCache
from service.db import transaction, upgrade
from service.settings import Settings
from service.tables import Job, Metric, Scene
from tests.helpers import api_client


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class Source:
    """A database stand-in: counts reads, can block them, answers the current value."""

    def __init__(self, value: bytes = b"v1"):
        self.value, self.reads, self.gate = value, 0, threading.Event()
        self.gate.set()

    def __call__(self) -> bytes:
        self.gate.wait(5)
        self.reads += 1
        return self.value


def run(coroutine):
    return asyncio.run(coroutine)


def test_an_answer_is_served_until_it_is_ttl_old_then_read_again():
    clock, source = Clock(), Source()
    cache = PollCache(0.5, clock=clock)

    async def go():
        assert await cache.job_view(1, source) == b"v1"
        source.value = b"v2"
        clock.now += 0.49
        assert await cache.job_view(1, source) == b"v1"  # still fresh
        clock.now += 0.01
        assert await cache.job_view(1, source) == b"v2"  # exactly ttl old: read again

    run(go())
    assert source.reads == 2 and (cache.hits, cache.misses) == (1, 2)


def test_concurrent_misses_share_one_read():
    source = Source()
    cache = PollCache(0.5, clock=Clock())

    async def go():
        source.gate.clear()  # the read is slow: every poller arrives while it is under way
        pollers = [asyncio.create_task(cache.job_view(7, source)) for _ in range(200)]
        await asyncio.sleep(0.05)
        source.gate.set()
        return await asyncio.gather(*pollers)

    assert run(go()) == [b"v1"] * 200
    assert source.reads == 1 and cache.misses == 1 and cache.hits == 199


def test_a_metrics_answer_is_dropped_when_the_job_view_changes():
    clock, view, series = Clock(), Source(b"step 10"), Source(b"metrics to 10")
    cache = PollCache(0.5, clock=clock)

    async def go():
        await cache.job_view(1, view)  # view read at t=100
        clock.now += 0.3
        # metrics read at t=100.3
        assert await cache.metrics(1, ("k",), view, series) == b"metrics to 10"
        # training writes step 20 (one transaction)
        view.value, series.value = b"step 20", b"metrics to 20"
        clock.now += 0.25  # the view is 0.55 s old (expired), the metrics answer only 0.25 s
        assert await cache.job_view(1, view) == b"step 20"
        # A poller that saw "step 20" must not get the answer computed under "step 10", fresh as it
        # is.
        assert await cache.metrics(1, ("k",), view, series) == b"metrics to 20"
        # now cached under "step 20"
        assert await cache.metrics(1, ("k",), view, series) == b"metrics to 20"

    run(go())
    assert series.reads == 2 and view.reads == 2


def test_forget_drops_entries_and_a_read_in_flight_is_not_stored():
    cache = PollCache(60.0, clock=Clock())

    async def go():
        assert await cache.job_view(3, Source(b"before cancel")) == b"before cancel"
        await cache.metrics(3, ("k",), Source(b"before cancel"), Source(b"m"))
        cache.forget(3)
        assert cache.entries == {}
        old = Source(b"before cancel")
        old.gate.clear()
        slow = asyncio.create_task(cache.job_view(3, old))  # a read begun before the next cancel
        await asyncio.sleep(0.05)
        await asyncio.to_thread(cache.forget, 3)  # a cancel handler in the threadpool
        fresh = await cache.job_view(3, Source(b"after cancel"))  # does not wait for the old read
        old.gate.set()
        return await slow, fresh, await cache.job_view(3, Source(b"never read"))

    slow, fresh, later = run(go())
    # the old read not kept
    assert (slow, fresh, later) == (b"before cancel", b"after cancel", b"after cancel")


def test_errors_reach_every_waiter_and_are_never_cached():
    clock = Clock()
    cache = PollCache(0.5, clock=clock)
    calls = []

    def failing() -> bytes:
        calls.append(1)
        raise RuntimeError("database unavailable")

    async def go():
        results = await asyncio.gather(
            *[cache.job_view(1, failing) for _ in range(5)], return_exceptions=True
        )
        assert all(isinstance(r, RuntimeError) for r in results)
        assert await cache.job_view(1, Source(b"back")) == b"back"

    run(go())
    assert len(calls) == 1


def test_ttl_zero_reads_every_time_and_the_size_is_bounded():
    source = Source()
    off = PollCache(0.0, clock=Clock())
    small = PollCache(10.0, max_entries=3, clock=Clock())

    async def go():
        for _ in range(3):
            await off.job_view(1, source)
        for job in range(10):
            await small.job_view(job, Source())

    run(go())
    assert source.reads == 3 and off.entries == {}
    assert list(small.entries) == [("job", 7), ("job", 8), ("job", 9)]


@pytest.fixture
def api(tmp_path):
    # long: only invalidation can refresh it
    settings = Settings(data_dir=tmp_path, poll_cache_s=30.0)
    upgrade(settings.db_url)
    # a registered scene; its files are never read here
    with transaction(settings.db_url) as session:
        session.add(Scene(name="s", source="synthetic", state="ready", path=str(tmp_path)))
    with api_client(settings) as client:
        job = client.post(
            "/v1/jobs", json={"scene": "s", "method": "switch", "profile": "smoke"}
        ).json()
        yield client, settings, job["id"]


def test_the_api_serves_a_cached_view_and_a_cancel_shows_at_once(api):
    client, settings, job_id = api
    first = client.get(f"/v1/jobs/{job_id}").json()
    with transaction(settings.db_url) as session:  # another process (training) writes progress
        session.get(Job, job_id).step = 5
    # cached: the same bytes
    assert client.get(f"/v1/jobs/{job_id}").json()["step"] == first["step"] == 0
    cancelled = client.post(f"/v1/jobs/{job_id}/cancel")
    assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
    shown = client.get(f"/v1/jobs/{job_id}").json()
    # this process's own write dropped the entry
    assert shown["state"] == "cancelled" and shown["step"] == 5
    assert client.get("/v1/jobs/999").status_code == 404
    prometheus = client.get("/metrics").text
    assert 'leco_poll_cache_total{result="hit"} 1' in prometheus


def test_the_api_metrics_answer_follows_the_job_view(api):
    client, settings, job_id = api
    assert client.get(f"/v1/jobs/{job_id}/metrics", params={"after_step": 0}).json()["series"] == []
    # what DatabaseRunStore.write does in one transaction
    with transaction(settings.db_url) as session:
        session.add(
            Metric(job_id=job_id, phase="main", name="loss", step=10, value=0.5, wall_time_s=1.0)
        )
        session.get(Job, job_id).step = 10
    # the view expired; the metrics answer has not
    del client.app.state.poll_cache.entries[("job", job_id)]
    assert client.get(f"/v1/jobs/{job_id}").json()["step"] == 10
    series = client.get(f"/v1/jobs/{job_id}/metrics", params={"after_step": 0}).json()["series"]
    assert [(s["name"], [p["step"] for p in s["points"]]) for s in series] == [("loss", [10])]


def test_job_lists_are_cached_and_every_change_through_this_process_shows_at_once(api):
    client, settings, job_id = api
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]] == [job_id]
    second = client.post(
        "/v1/jobs", json={"scene": "s", "method": "grid", "profile": "smoke"}
    ).json()["id"]
    # submit dropped the list
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]] == [second, job_id]
    with transaction(settings.db_url) as session:  # another process moves a job on
        session.get(Job, job_id).step = 7
    assert client.get("/v1/jobs").json()["items"][1]["step"] == 0  # served from the cache meanwhile
    # another key: read
    assert client.get("/v1/jobs", params={"state": "queued"}).json()["total"] == 2
    client.post(f"/v1/jobs/{second}/cancel")
    listed = client.get("/v1/jobs").json()["items"]
    assert [(j["id"], j["state"], j["step"]) for j in listed] == [
        (second, "cancelled", 0),
        (job_id, "queued", 7),
    ]
    assert client.get("/v1/jobs", params={"state": "queued"}).json()["total"] == 1


def test_memory_stays_bounded_however_many_jobs_are_polled_and_written():
    cache = PollCache(0.5, max_entries=64, clock=Clock())

    async def scenario():
        for job in range(1, 5001):
            await cache.job_view(job, Source(b"view"))
            cache.forget(job)  # a submit or cancel of each job
            await cache.job_view(job, Source(b"view"))

    run(scenario())
    assert len(cache.entries) == 64 and not cache.in_flight
    sizes = {name: len(value) for name, value in vars(cache).items() if hasattr(value, "__len__")}
    # no per-job record left behind (there was one epoch per job)
    assert max(sizes.values()) <= 64, sizes
