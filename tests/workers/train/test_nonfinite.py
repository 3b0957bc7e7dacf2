"""The non-finite guard on the device: the flag, the streak, and a real step of the loop whose loss
or one gradient is NaN, which must leave every parameter and every Adam state as it was."""

import pytest
import torch

from model.methods.parts import read_parts
from model.profiles import MAX_STEPS
from workers.config import TrainConfig
from workers.train.loop import RankRun
from workers.train.nonfinite import NonfiniteStreak, nonfinite
from workers.train.session import LocalSession


def test_the_flag_finds_a_single_nan_or_inf_in_the_loss_or_any_gradient():
    params = [torch.nn.Parameter(torch.zeros(4, 4)) for _ in range(3)] + [
        torch.nn.Parameter(torch.zeros(2))
    ]
    for p in params[:3]:  # the last keeps no gradient, as an expert no ray reached
        p.grad = torch.randn(4, 4, generator=torch.Generator().manual_seed(0)) * 1e6
    loss = torch.tensor(0.5)
    assert nonfinite(loss, params).item() == 0.0 and nonfinite(loss, [params[3]]).item() == 0.0
    for bad in (float("nan"), float("inf"), -float("inf")):
        params[1].grad[2, 3] = bad
        assert nonfinite(loss, params).item() == 1.0
        params[1].grad[2, 3] = 0.0
        assert nonfinite(torch.tensor(bad), params).item() == 1.0
    assert nonfinite(loss, params).dtype == torch.float32  # as Adam's found_inf


def test_the_streak_keeps_the_longest_run_since_the_last_read_and_carries_the_running_one():
    streak = NonfiniteStreak(2, torch.device("cpu"))  # a resumed run's streak
    for skipped in (1, 1, 0, 1):
        streak.add(torch.tensor(float(skipped)))
    assert streak.read() == (4, 1)
    assert streak.running() == 1
    streak.add(torch.tensor(1.0))
    assert streak.read() == (2, 2)
    streak.add(torch.tensor(0.0))
    assert streak.read() == (2, 0)  # the streak that ran into this window still counts once
    assert streak.read() == (0, 0)


def snapshot(run: RankRun) -> tuple[list[torch.Tensor], list[dict]]:
    objects = run.current_phase()
    params = [p.detach().clone() for p in objects.params]
    state = [
        {k: v.clone() for k, v in objects.optimizer.state[p].items()}
        for p in objects.params
        if p in objects.optimizer.state
    ]
    return params, state


def assert_unchanged(run: RankRun, before: tuple[list[torch.Tensor], list[dict]]) -> None:
    params, state = snapshot(run)
    assert all(torch.equal(a, b) for a, b in zip(params, before[0]))
    assert len(state) == len(before[1])
    for now, then in zip(state, before[1]):
        assert now.keys() == then.keys()
        assert all(torch.equal(now[k], then[k]) for k in now)


@pytest.mark.parametrize("poison", ["loss", "gradient"])
def test_a_step_with_a_nan_loss_or_gradient_changes_no_parameter_and_no_adam_state(
    tiny_scene, tmp_path, monkeypatch, poison
):
    import model.methods.main_phase as main_phase

    cfg = TrainConfig(
        method="switch", profile="smoke", metrics_every=MAX_STEPS, checkpoint_every=MAX_STEPS
    )
    run = RankRun(
        cfg, tiny_scene.root, tmp_path / "run", LocalSession(tmp_path / "s"), torch.device("cpu")
    )
    run.start_phase("main", fresh=True)
    objects = run.current_phase()
    assert read_parts(run.train_step("main", objects))["skipped"] == 0.0  # Adam's state exists
    before = snapshot(run)

    if poison == "loss":
        real = main_phase.rendering_loss
        monkeypatch.setattr(main_phase, "rendering_loss", lambda *a: real(*a) * float("nan"))
        parts = run.train_step("main", objects)
        monkeypatch.setattr(main_phase, "rendering_loss", real)
    else:  # one entry of the input layer's gradient, the loss finite
        weight = run.models.field.input_layer.weight

        def one_nan(grad: torch.Tensor) -> torch.Tensor:
            grad = grad.clone()
            grad[0, 0] = float("nan")
            return grad

        handle = weight.register_hook(one_nan)
        parts = run.train_step("main", objects)
        handle.remove()
        assert read_parts(parts)["loss"] == read_parts(parts)["loss"]  # finite

    assert read_parts(parts)["skipped"] == 1.0
    assert_unchanged(run, before)
    assert run.progress["step"] == 2  # counted as a step, as before the guard moved

    assert read_parts(run.train_step("main", objects))["skipped"] == 0.0
    params, _ = snapshot(run)
    assert not all(torch.equal(a, b) for a, b in zip(params, before[0]))
    assert run.nonfinite.read() == (1, 0)
