"""A step draws the run's own stream through the default generator, and nothing else sees it."""

import pytest
import torch

from model.methods.parts import read_parts
from workers.config import TrainConfig
from workers.train.lent_generator import default_generator, lent
from workers.train.loop import RankRun
from workers.train.session import LocalSession


def test_inside_the_loan_the_default_generator_draws_the_run_generators_numbers():
    run = torch.Generator().manual_seed(7)
    expected = torch.rand(5, generator=torch.Generator().manual_seed(7))
    torch.manual_seed(0)
    outside = torch.rand(3, generator=torch.Generator().manual_seed(0))
    with lent(run):
        assert torch.equal(torch.rand(5), expected)
    # the run's stream moved on by those five draws, and the default one did not move at all
    follow = torch.Generator().manual_seed(7)
    torch.rand(5, generator=follow)
    assert torch.equal(torch.rand(4, generator=run), torch.rand(4, generator=follow))
    assert torch.equal(torch.rand(3), outside)


def test_a_failing_step_still_hands_the_stream_back():
    run = torch.Generator().manual_seed(1)
    torch.manual_seed(2)
    with pytest.raises(RuntimeError, match="inside"), lent(run):
        torch.rand(8)
        raise RuntimeError("inside")
    assert torch.equal(torch.rand(2), torch.rand(2, generator=torch.Generator().manual_seed(2)))
    follow = torch.Generator().manual_seed(1)
    torch.rand(8, generator=follow)
    assert run.get_state().equal(follow.get_state())


def test_the_default_generator_is_the_one_torch_rand_uses_on_the_cpu():
    assert default_generator(torch.device("cpu")) is torch.default_generator
    with pytest.raises(ValueError, match="no default generator is known for device 'meta'"):
        default_generator(torch.device("meta"))


@pytest.mark.parametrize("method", ["switch", "prop"])
def test_a_step_depends_on_the_run_seed_and_not_on_the_global_one(tiny_scene, tmp_path, method):
    """Switch-NeRF's density noise and the samplers' jitter come from the rank's own generator,
    whatever the global one holds."""
    losses = []
    for k, global_seed in enumerate((11, 12345)):
        cfg = TrainConfig(method=method, profile="smoke", metrics_every=1000)
        run_dir = tmp_path / f"run{k}"
        run = RankRun(
            cfg, tiny_scene.root, run_dir, LocalSession(run_dir / "s"), torch.device("cpu")
        )
        run.progress.update(phase="main", phase_step=0)
        run.start_phase("main", fresh=True)
        torch.manual_seed(global_seed)
        parts = [run.train_step("main", run.current_phase()) for _ in range(3)]
        losses.append([read_parts(p) for p in parts])
    assert losses[0] == losses[1]
