"""Where a run's ray batches are made: the choice by device and size, and the prefetching thread
that draws a host sampler ahead without changing a batch or a resumed run's next one."""

import pytest
import torch

from model.scenes import RaySampler
from tests.model.scenes.test_rays import AABB, small_views
from workers.train.ray_batches import PrefetchedRays, ray_batches, resident_bytes


def batches_equal(a, b) -> bool:
    return all(torch.equal(value, getattr(b, name)) for name, value in a.__dict__.items())


def test_a_cpu_run_draws_on_the_host_whatever_the_bound():
    views = small_views()  # 144 pixels
    assert resident_bytes(views) == 144 * 7
    for bound in (0.0, 4096.0):
        sampler = ray_batches(views, AABB, 16, 0, 0, 1, torch.device("cpu"), bound)
        assert isinstance(sampler, RaySampler) and not sampler.resident


def test_prefetched_batches_are_the_samplers_and_its_state_the_last_one_handed_out():
    views = small_views()
    plain = RaySampler(views, AABB, batch_size=16, seed=3)
    ahead = PrefetchedRays(RaySampler(views, AABB, batch_size=16, seed=3), torch.device("cpu"))
    try:
        for k in range(12):  # past an epoch's end (9 batches)
            assert batches_equal(ahead.next(), plain.next()), k
            # the thread has drawn further; the state is where the step is
            assert ahead.state_dict() == plain.state_dict(), k
        # a checkpoint taken now resumes with the step's next batch, not the thread's
        resumed = PrefetchedRays(RaySampler(views, AABB, 16, 3), torch.device("cpu"))
        resumed.load_state_dict(ahead.state_dict())
        expected = plain.next()
        assert batches_equal(resumed.next(), expected)
        assert batches_equal(ahead.next(), expected)
        resumed.close()
    finally:
        ahead.close()
    assert ahead._thread is None


def test_loading_a_state_mid_run_drops_what_the_thread_drew_ahead():
    views = small_views()
    ahead = PrefetchedRays(RaySampler(views, AABB, batch_size=16, seed=5), torch.device("cpu"))
    first = [ahead.next() for _ in range(3)]
    ahead.load_state_dict({"seed": 5, "epoch": 0, "offset": 16, "batch_size": 16})
    try:
        assert batches_equal(ahead.next(), first[1])
        assert batches_equal(ahead.next(), first[2])
    finally:
        ahead.close()


def test_an_error_while_drawing_reaches_the_step():
    views = small_views()

    class Broken(RaySampler):
        def next(self):
            raise OSError("pixel cache unreadable")

    ahead = PrefetchedRays(Broken(views, AABB, batch_size=16, seed=0), torch.device("cpu"))
    with pytest.raises(OSError, match="pixel cache unreadable"):
        ahead.next()
    ahead.close()
