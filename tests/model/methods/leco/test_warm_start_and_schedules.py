"""Warm start of LeCO's main phase from phase 1, and learning-rate / w_g schedules that end with the
budget."""

import pytest
import torch

from model.methods import get_method
from model.methods.leco.warm_start import warm_start_main
from model.methods.schedules import log_linear, phase_progress
from workers.config import TrainConfig
from workers.models import build_models, build_optimizer
from workers.train.run import run_training
from workers.train.sinks import read_metrics


def test_schedules_reach_their_final_value_at_the_end_of_steps_or_time():
    assert log_linear(2e-3, 2e-4, 0.0) == 2e-3 and log_linear(2e-3, 2e-4, 1.0) == pytest.approx(
        2e-4
    )
    assert log_linear(2e-3, 2e-4, 0.5) == pytest.approx((2e-3 * 2e-4) ** 0.5)
    assert log_linear(5e-4, None, 0.7) == 5e-4  # the paper's constant phase-1 rate
    assert log_linear(0.1, 0.0, 0.25) == pytest.approx(0.075)  # to zero: linear
    # With a budget the step count may be unbounded: time decides.
    assert phase_progress(100, 10_000_000, 30.0, 120.0) == pytest.approx(0.25)
    assert phase_progress(900, 1000, 1.0, 120.0) == pytest.approx(0.9)  # steps end first
    assert phase_progress(5, 10, 500.0, None) == 0.5 and phase_progress(50, 10, 0.0, None) == 1.0


def test_optimizer_lr_follows_the_profile(tiny_scene):
    cfg = TrainConfig(method="leco", profile="smoke", overrides={"occupancy.lr_final": 5e-5})
    profile = cfg.resolved_profile()
    models = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    )
    _, _, lr_at = build_optimizer(get_method("leco")(profile), models, "occupancy")
    assert lr_at(0.0) == profile.occupancy.lr and lr_at(1.0) == pytest.approx(5e-5)
    _, _, lr_at = build_optimizer(get_method("leco")(profile), models, "main")
    assert lr_at(1.0) == pytest.approx(profile.lr_final)


def test_budgeted_run_ends_its_main_phase_at_lr_final(tiny_scene, tmp_path):
    cfg = TrainConfig(
        method="switch",
        profile="smoke",
        budget_min=1.5 / 60,
        metrics_every=1,
        overrides={"main_steps": 10_000_000},
    )
    run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    rows = read_metrics(tmp_path / "run" / "metrics.jsonl")
    profile = cfg.resolved_profile()
    assert rows[0]["lr"] == pytest.approx(profile.lr, rel=0.05)
    # The last step started within one step of the budget's end, so its lr is lr_final to within one
    # step's share of the log-linear schedule (half a step more for jitter). The step is measured,
    # not assumed: beside another pytest worker the last step began 6% of the budget before its end.
    step_s = max(b["wall_time_s"] - a["wall_time_s"] for a, b in zip(rows[-11:], rows[-10:]))
    share = 1.5 * step_s / (cfg.budget_min * 60)
    ceiling = profile.lr_final * (profile.lr / profile.lr_final) ** share
    assert profile.lr_final * 0.99 <= rows[-1]["lr"] <= ceiling, (rows[-1]["lr"], step_s)


def test_warm_start_copies_phase_one_into_the_main_network(tiny_scene):
    profile = TrainConfig(method="leco", profile="smoke").resolved_profile()
    models = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    )
    hmoe, field = models.hmoe, models.field
    copied = warm_start_main(field, models.background, hmoe, models.occupancy_background)
    assert set(copied) >= {
        "input_layer",
        "head",
        "appearance",
        "background",
        "gate.proj",
        "experts.0",
        "experts.1",
    }
    for a, b in zip(field.experts, hmoe.scene_experts):
        assert all(
            torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values())
        )
    assert torch.equal(
        models.background.trunk[0].weight, models.occupancy_background.trunk[0].weight
    )
    # Every point a scene expert rendered in phase 1 goes to the same expert in the main network.
    xyz = torch.rand(2000, 3) * 2 - 1
    with torch.no_grad():
        logits = hmoe.gate(xyz)
        scene = logits.argmax(-1) != hmoe.gate.empty_index
        routed = field.gate(field.input_layer(field.xyz_encoding(xyz))).argmax(-1)
    assert scene.any() and torch.equal(routed[scene], logits[scene].argmax(-1))


def test_a_warm_start_without_phase_one_s_background_leaves_the_main_background_fresh(tiny_scene):
    profile = TrainConfig(method="leco", profile="smoke").resolved_profile()
    models = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    )
    fresh = {k: v.clone() for k, v in models.background.state_dict().items()}
    copied = warm_start_main(models.field, models.background, models.hmoe, None)
    assert "background" not in copied and {"input_layer", "head", "experts.0"} <= set(copied)
    assert all(torch.equal(fresh[k], v) for k, v in models.background.state_dict().items())
    assert not torch.equal(
        models.background.trunk[0].weight, models.occupancy_background.trunk[0].weight
    )


def test_a_warm_start_without_phase_one_s_density_copies_the_colours_only(tiny_scene):
    profile = TrainConfig(method="leco", profile="smoke").resolved_profile()
    models = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    )
    fresh = {k: v.clone() for k, v in models.field.head.sigma.state_dict().items()}
    copied = warm_start_main(models.field, models.background, models.hmoe, None, density=False)
    assert "head (colour only)" in copied and "head" not in copied
    assert all(torch.equal(fresh[k], v) for k, v in models.field.head.sigma.state_dict().items())
    assert torch.equal(models.field.head.feature.weight, models.hmoe.scene_head.feature.weight)
    assert not torch.equal(models.field.head.sigma.weight, models.hmoe.scene_head.sigma.weight)


def test_a_wider_occupancy_network_saves_loads_and_warm_starts_what_still_fits(
    tiny_scene, tmp_path
):
    from model.estimators.occupancy import OccupancyPredictor

    profile = TrainConfig(
        method="leco", profile="smoke", overrides={"occupancy.gate_width": 32}
    ).resolved_profile()
    models = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    )
    gate = models.hmoe.gate
    # experts stay 16 wide
    assert gate.input_layer.out_features == 16 and gate.inner[0].weight.shape == (32, 16)
    # inner, LayerNorm, 2 experts + E_e logits
    own = lambda w: (16 * w + w) + (w * w + w) + 2 * w + (w * 3 + 3)
    narrow = build_models(
        get_method("leco")(TrainConfig(method="leco", profile="smoke").resolved_profile()),
        tiny_scene.num_images,
        tiny_scene.bounds.aabb,
        0,
    ).hmoe.gate
    count = lambda m: sum(p.numel() for p in m.parameters())
    assert count(gate) - count(narrow) == own(32) - own(16)
    predictor = OccupancyPredictor.from_hmoe(models.hmoe, empty_threshold=0.9)
    predictor.save(tmp_path / "o.pt")
    loaded = OccupancyPredictor.load(tmp_path / "o.pt", empty_threshold=0.9)
    xyz = torch.rand(500, 3) * 2 - 1
    assert torch.equal(loaded.occupied(xyz), predictor.occupied(xyz))
    copied = warm_start_main(
        models.field, models.background, models.hmoe, models.occupancy_background
    )
    # the shared parts still match the main network
    assert "experts.0" in copied and "input_layer" in copied
    assert not any(name.startswith("gate.body") for name in copied) and "gate.proj" not in copied


def test_warm_started_leco_run_starts_its_main_phase_where_phase_one_ended(tiny_scene, tmp_path):
    """The main phase's first loss is far below a from-scratch start's when phase 1 has learned the
    scene."""
    first_main_loss = {}
    for warm in (False, True):
        cfg = TrainConfig(
            method="leco",
            profile="smoke",
            metrics_every=1,
            seed=0,
            overrides={
                "occupancy.steps": 150,
                "main_steps": 1,
                "guided.warm_start": warm,
                "guided.fallback": True,
            },
        )
        run_training(cfg, tiny_scene.root, tmp_path / f"run-{warm}", backend="local")
        rows = read_metrics(tmp_path / f"run-{warm}" / "metrics.jsonl")
        first_main_loss[warm] = [r for r in rows if r["phase"] == "main"][0]["rendering_loss"]
    assert first_main_loss[True] < 0.7 * first_main_loss[False]


def test_relu_on_every_layer_of_o_is_a_different_function_that_saves_and_loads(
    tiny_scene, tmp_path
):
    from model.estimators.occupancy import OccupancyPredictor

    overrides = {"occupancy.gate_relu_every_layer": True}
    profile = TrainConfig(method="leco", profile="smoke", overrides=overrides).resolved_profile()
    hmoe = build_models(
        get_method("leco")(profile), tiny_scene.num_images, tiny_scene.bounds.aabb, 0
    ).hmoe
    plain = build_models(
        get_method("leco")(TrainConfig(method="leco", profile="smoke").resolved_profile()),
        tiny_scene.num_images,
        tiny_scene.bounds.aabb,
        0,
    ).hmoe
    # same keys and weights: only the activations differ
    plain.gate.load_state_dict(hmoe.gate.state_dict())
    xyz = torch.rand(500, 3) * 2 - 1
    with torch.no_grad():
        assert (hmoe.gate(xyz) - plain.gate(xyz)).abs().max() > 1e-3
    predictor = OccupancyPredictor.from_hmoe(hmoe, empty_threshold=0.9)
    predictor.save(tmp_path / "o.pt")
    loaded = OccupancyPredictor.load(tmp_path / "o.pt", empty_threshold=0.9)
    assert loaded.network.relu_every_layer
    with torch.no_grad():
        assert torch.equal(loaded.network(xyz), hmoe.gate(xyz))


def test_after_a_warm_start_the_main_lr_ramps_up_over_its_steps(tiny_scene, tmp_path):
    """guided.warm_start_ramp: main-phase step k (0-based) trains at (k + 1) / ramp of its
    schedule's lr."""
    ramp, main_steps = 8, 12
    cfg = TrainConfig(
        method="leco",
        profile="smoke",
        metrics_every=1,
        overrides={
            "guided.warm_start": True,
            "guided.warm_start_ramp": ramp,
            "main_steps": main_steps,
        },
    )
    run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    profile = cfg.resolved_profile()
    method = get_method("leco")(profile)
    _, _, lr_at = build_optimizer(
        method, build_models(method, tiny_scene.num_images, tiny_scene.bounds.aabb, 0), "main"
    )
    main = [r for r in read_metrics(tmp_path / "run" / "metrics.jsonl") if r["phase"] == "main"]
    assert len(main) == main_steps
    for k, row in enumerate(main):
        assert row["lr"] == pytest.approx(
            lr_at(k / main_steps) * min(1.0, (k + 1) / ramp), rel=1e-6
        ), k
