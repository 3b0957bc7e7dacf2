"""O learning during the main phase (guided.online): which bins teach what, that the signal finds a
surface O missed, and that a LeCO run with it trains, saves the O it ended with and reports O's
loss."""

import json

import pytest
import torch
import torch.nn.functional as F

from model.estimators import online as online_module
from model.estimators.guided import guided_samples
from model.estimators.occupancy import OccupancyPredictor
from model.estimators.online import OnlineOccupancy
from model.fields.hmoe import OccupancyNetwork
from model.render.noise import Noise
from model.render.samples import PackedSamples
from model.render.volume import packed_weights
from model.scenes.rays import RayBatch
from workers.config import TrainConfig
from workers.train.run import run_training
from workers.train.sinks import read_metrics

# along x; coarse bins of [0, 8] are 1 wide, so the wall lies inside bin 4, around its mid-point
WALL = (4.2, 4.8)


def ray_batch(n: int) -> RayBatch:
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(
        torch.tensor([1.0, 0, 0]) + 0.05 * torch.randn(n, 3, generator=g), dim=-1
    )
    # not unit: a step of 1 in t is 1 in x, so the bins are the same in x on every ray
    dirs = dirs / dirs[:, :1]
    zeros = torch.zeros(n)
    return RayBatch(
        origins=torch.zeros(n, 3),
        directions=dirs,
        near=zeros,
        far=zeros + 8.0,
        rgb=torch.zeros(n, 3),
        image_index=torch.zeros(n, dtype=torch.long),
        pixel=torch.arange(n),
    )


def test_kept_bins_teach_surface_and_seen_through_space_and_nothing_else():
    rays = ray_batch(1)
    # Samples in bins 0, 1 and 2 of 4 (bin 3 skipped); bin 1 holds the surface, bin 2 lies behind
    # it.
    samples = PackedSamples(
        torch.tensor([0.5, 2.5, 4.5]),
        torch.tensor([1.0, 3.0, 5.0]),
        torch.zeros(3, dtype=torch.long),
    )
    weights = torch.tensor([0.004, 0.8, 0.003])
    online = OnlineOccupancy(OccupancyNetwork(2, 16, 4), empty_threshold=0.9)
    target, mask = online.bin_targets(samples, weights, rays, num_coarse=4)
    assert target.tolist() == [[0.0, 1.0, 0.0, 0.0]]
    # bin 2 is hidden behind the surface, bin 3 unseen
    assert mask.tolist() == [[True, True, False, False]]


def test_no_bin_is_free_on_a_ray_whose_foreground_is_semi_transparent():
    # Ray 0's foreground is opaque (0.9 in bin 1): bin 0 in front of it is free. Ray 1's foreground
    # holds 0.3 in all (the background paints the rest): with free_opacity 0.5 its empty-looking bin
    # 0 teaches nothing.
    rays = ray_batch(2)
    samples = PackedSamples(
        torch.tensor([0.5, 2.5, 0.5, 2.5]),
        torch.tensor([1.0, 3.0, 1.0, 3.0]),
        torch.tensor([0, 0, 1, 1]),
    )
    weights = torch.tensor([0.01, 0.89, 0.01, 0.29])
    loose = OnlineOccupancy(OccupancyNetwork(2, 16, 4), empty_threshold=0.9)
    strict = OnlineOccupancy(OccupancyNetwork(2, 16, 4), empty_threshold=0.9, free_opacity=0.5)
    target, mask = loose.bin_targets(samples, weights, rays, num_coarse=4)
    assert target.tolist() == [[0.0, 1.0, 0.0, 0.0]] * 2 and mask[:, 0].tolist() == [True, True]
    target, mask = strict.bin_targets(samples, weights, rays, num_coarse=4)
    # ray 1: its surface only
    assert mask.tolist() == [[True, True, False, False], [False, True, False, False]]


def test_no_bin_is_free_on_a_ray_the_field_still_renders_wrong():
    # Both rays hold 0.9 in bin 1, so bin 0 in front looks free. Ray 1 renders its pixel 0.3 off
    # in every channel (squared error 0.09): with free_error 0.01 its bin 0 teaches nothing, as a
    # roof's top the field has not fitted yet is not taught free by the rays that graze it.
    rays = ray_batch(2)
    rays.rgb = torch.full((2, 3), 0.5)
    rendered = torch.tensor([[0.52, 0.5, 0.48], [0.8, 0.8, 0.8]])
    samples = PackedSamples(
        torch.tensor([0.5, 2.5, 0.5, 2.5]),
        torch.tensor([1.0, 3.0, 1.0, 3.0]),
        torch.tensor([0, 0, 1, 1]),
    )
    weights = torch.tensor([0.01, 0.89, 0.01, 0.89])
    strict = OnlineOccupancy(OccupancyNetwork(2, 16, 4), empty_threshold=0.9, free_error=0.01)
    target, mask = strict.bin_targets(samples, weights, rays, 4, rendered)
    assert target.tolist() == [[0.0, 1.0, 0.0, 0.0]] * 2
    assert mask.tolist() == [[True, True, False, False], [False, True, False, False]]
    with pytest.raises(ValueError, match="free_error needs the rays' rendered colours"):
        strict.bin_targets(samples, weights, rays, 4)


def slab_density(points: torch.Tensor, slabs: list[tuple[float, float]]) -> torch.Tensor:
    x = points[:, 0]
    inside = torch.zeros_like(x, dtype=torch.bool)
    for lo, hi in slabs:
        inside |= (x > lo) & (x < hi)
    return torch.where(inside, 50.0, 0.0)


def online_steps(
    online, optimizer, rays, noise, slabs, steps: int, explore: int = 0, topk: int = 2
) -> None:
    """`steps` of O's online loss under LeCO's sampler (jitter, dilation 1, the fallback: with
    `topk` 2, `cpu`'s) on a main network that is exactly the given slabs."""
    for _ in range(steps):
        samples, _ = guided_samples(
            rays.near,
            rays.far,
            rays.origins,
            rays.directions,
            online.occupied,
            8,
            4,
            noise,
            online.scores,
            jitter=True,
            dilate=1,
            fallback=True,
            topk=topk,
            explore=explore,
        )
        xyz = (
            rays.origins[samples.ray_index]
            + rays.directions[samples.ray_index] * samples.mids[:, None]
        )
        density = slab_density(xyz, slabs)
        weights, _ = packed_weights(density, samples.deltas, samples.ray_index, len(rays))
        loss = online.loss(samples, weights, rays, num_coarse=8)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def test_o_that_keeps_nothing_learns_the_wall_the_main_network_sees():
    torch.manual_seed(0)
    network = OccupancyNetwork(num_scene_experts=2, width=32, xyz_frequencies=4)
    with torch.no_grad():
        network.output.bias[network.empty_index] = 8.0  # O starts sure that everything is empty
    online = OnlineOccupancy(network, empty_threshold=0.9)
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-2)
    rays, noise = ray_batch(128), Noise(torch.Generator().manual_seed(1))
    free_x = torch.linspace(0.2, 3.8, 50)
    free = torch.stack([free_x, torch.zeros(50), torch.zeros(50)], -1)
    wall = torch.stack(
        [torch.linspace(WALL[0] + 0.02, WALL[1] - 0.02, 50), torch.zeros(50), torch.zeros(50)], -1
    )
    assert not network.occupied(wall, 0.9).any()
    # the fallback samples every bin of a ray O keeps nothing of
    online_steps(online, optimizer, rays, noise, [WALL], 150, topk=0)
    assert network.occupied(wall, 0.9).float().mean() >= 0.9
    assert network.occupied(free, 0.9).float().mean() <= 0.2


# a ground in the last bin and a wall far in front of it: an O that learned only the ground keeps
# bins 6-7 (dilated) and, jittered queries and all, never shows the main network bin 2
GROUND, FRONT = (7.2, 7.8), (2.2, 2.8)


@pytest.mark.parametrize("explore", [0, 2])
def test_explored_bins_teach_o_a_wall_its_keep_never_shows(explore):
    # O first learns a scene that is only the ground; then a wall appears in front of it (a tree
    # crown the main network learns late). O keeps bins 6-7, so without exploration no ray samples
    # bin 2 and O stays blind to the wall; two random dropped bins a ray find it and teach it.
    torch.manual_seed(0)
    network = OccupancyNetwork(num_scene_experts=2, width=32, xyz_frequencies=4)
    online = OnlineOccupancy(network, empty_threshold=0.9)
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-2)
    rays, noise = ray_batch(128), Noise(torch.Generator().manual_seed(1))
    line = lambda lo, hi: torch.stack(  # noqa: E731
        [torch.linspace(lo + 0.02, hi - 0.02, 50), torch.zeros(50), torch.zeros(50)], -1
    )
    online_steps(online, optimizer, rays, noise, [GROUND], 150, explore=0)
    assert network.occupied(line(*GROUND), 0.9).float().mean() >= 0.9
    assert network.occupied(line(*FRONT), 0.9).float().mean() <= 0.1
    online_steps(online, optimizer, rays, noise, [FRONT, GROUND], 150, explore=explore)
    kept = network.occupied(line(*FRONT), 0.9).float().mean()
    if explore:
        assert kept >= 0.9
    else:
        assert kept <= 0.1


def online_losses(tiny_scene, run, overrides: dict) -> dict[int, float]:
    """A smoke LeCO run keeping bins where p(E_e) < 0.9 with `overrides`: O's online loss by the
    main-phase step it learned on."""
    cfg = TrainConfig(
        method="leco",
        profile="smoke",
        metrics_every=1,
        seed=0,
        overrides={"guided.empty_threshold": 0.9, **overrides},
    )
    run_training(cfg, tiny_scene.root, run, backend="local")
    rows = [r for r in read_metrics(run / "metrics.jsonl") if r["phase"] == "main"]
    return {
        r["phase_step"]: r["occupancy_online_loss"] for r in rows if "occupancy_online_loss" in r
    }


def test_a_leco_run_with_online_o_trains_it_saves_it_and_reports_its_loss(tiny_scene, tmp_path):
    final_o = {}
    # O learns from the 5th main step (warm-up 4), then every step or every 3rd one
    expected = {(False, 1): [], (True, 1): list(range(5, 11)), (True, 3): [5, 8]}
    for (online, every), learns_at in expected.items():
        run = tmp_path / f"run-{online}-{every}"
        learned = online_losses(
            tiny_scene,
            run,
            {
                "occupancy.steps": 20,
                "main_steps": 10,
                "guided.online": online,
                "guided.online_warmup": 4,
                "guided.online_every": every,
                "guided.fallback": True,
            },
        )
        assert list(learned) == learns_at
        assert all(torch.isfinite(torch.tensor(x)) for x in learned.values())
        saved = OccupancyPredictor.load(run / "final" / "occupancy.pt")
        models = torch.load(run / "final" / "models.pt", weights_only=False)["models"]
        # the saved O is the HMoE's gate as it ended
        for key, value in saved.network.state_dict().items():
            assert torch.equal(value, models[f"hmoe.gate.{key}"])
        final_o[online, every] = saved.network.state_dict()
    # Same seed, same phase 1: only the main phase's learning can have moved O, and fewer steps
    # moved it less.
    frozen = final_o[False, 1]
    moved = {
        key: sum(float((o[k] - frozen[k]).abs().sum()) for k in frozen)
        for key, o in final_o.items()
    }
    assert moved[False, 1] == 0 and 0 < moved[True, 3] < moved[True, 1]


@pytest.mark.parametrize("fine", [0, 12])  # one pass; two (model/estimators/fine_placement.py)
def test_a_leco_run_where_o_places_the_samples_learns_the_placement_in_both_phases(
    tiny_scene, tmp_path, fine
):
    cfg = TrainConfig(
        method="leco",
        profile="smoke",
        metrics_every=1,
        seed=0,
        overrides={
            "occupancy.steps": 12,
            "main_steps": 8,
            "guided.placement": True,
            "guided.main_samples": 6,
            "guided.placement_fine": fine,
            "guided.placement_in_phase1": True,
            "guided.fallback": True,
            "guided.fallback_topk": 2,
            "guided.dilate": 1,
            "guided.warm_start": True,
            "guided.warm_start_background": False,
        },
    )
    run = tmp_path / "run"
    run_training(cfg, tiny_scene.root, run, backend="local")
    rows = read_metrics(run / "metrics.jsonl")
    first = [r for r in rows if r["phase"] == "occupancy"]
    main = [r for r in rows if r["phase"] == "main"]
    assert all(r["placement_loss"] >= 0 for r in first)
    assert all(r["samples_per_hit_ray"] == 6 for r in main)  # a fixed budget per hit ray
    assert all(0 < r["occupancy_ratio"] <= 1 and 0 <= r["fallback_fraction"] <= 1 for r in main)
    saved = OccupancyPredictor.load(run / "final" / "occupancy.pt")
    assert saved.network.placement is not None  # the standalone O carries its placement head
    summary = json.loads((run / "summary.json").read_text())
    assert (
        summary["sampling"]["samples_per_hit_ray"] == 6
        and summary["rays"]["samples_per_hit_ray"] == 6
    )


@pytest.mark.parametrize("fine", [0, 12])
def test_o_places_without_gradient_between_its_placement_updates(tiny_scene, tmp_path, fine):
    cfg = TrainConfig(
        method="leco",
        profile="smoke",
        metrics_every=1,
        seed=0,
        overrides={
            "occupancy.steps": 6,
            "main_steps": 8,
            "guided.placement": True,
            "guided.main_samples": 6,
            "guided.placement_fine": fine,
            "guided.placement_every": 3,
            "guided.online": False,
            "guided.fallback": True,
            "guided.warm_start": True,
        },
    )
    run = tmp_path / "run"
    run_training(cfg, tiny_scene.root, run, backend="local")
    main = [r for r in read_metrics(run / "metrics.jsonl") if r["phase"] == "main"]
    # phase_step is counted after the step: main steps 0, 3 and 6 learn, the others only place
    assert [r["phase_step"] for r in main if "occupancy_online_loss" in r] == [1, 4, 7]
    assert all(r["samples_per_hit_ray"] == 6 for r in main)


def test_the_decision_logit_is_positive_exactly_where_the_sampler_keeps_the_point():
    network = OccupancyNetwork(num_scene_experts=3, width=16, xyz_frequencies=2)
    logits = torch.randn(2000, 4, generator=torch.Generator().manual_seed(0)) * 3
    for threshold in (None, 0.5, 0.9):
        online = OnlineOccupancy(network, empty_threshold=threshold)
        assert torch.equal(online.decision_logit(logits) > 0, network.decide(logits, threshold))


def test_surface_points_are_each_opaque_rays_most_visible_sample():
    # ray 0 is opaque and shows its second sample most; ray 1's foreground holds 0.3 (the
    # background paints the rest): it teaches no point
    rays = ray_batch(2)
    samples = PackedSamples(
        torch.tensor([0.5, 4.4, 6.0, 0.5, 2.5]),
        torch.tensor([1.0, 4.6, 6.5, 1.0, 3.0]),
        torch.tensor([0, 0, 0, 1, 1]),
    )
    weights = torch.tensor([0.01, 0.85, 0.10, 0.01, 0.29])
    online = OnlineOccupancy(OccupancyNetwork(2, 16, 4), 0.9, surface_points=True)
    points = online.shown_points(samples, weights, rays)
    assert points.shape == (1, 3)
    expected = rays.origins[0] + rays.directions[0] * 4.5
    assert torch.allclose(points[0], expected)


def sure_empty_network() -> OccupancyNetwork:
    """A seeded O that starts sure that everything is empty."""
    torch.manual_seed(0)
    network = OccupancyNetwork(num_scene_experts=2, width=32, xyz_frequencies=4)
    with torch.no_grad():
        network.output.bias[network.empty_index] = 8.0
    return network


def same_on_every_ray(starts: list[float], ends: list[float], count: int) -> PackedSamples:
    """The same samples (starts, ends) on each of `count` rays."""
    per_ray = len(starts)
    return PackedSamples(
        torch.tensor(starts).repeat(count),
        torch.tensor(ends).repeat(count),
        torch.arange(count).repeat_interleave(per_ray),
    )


def test_the_point_loss_teaches_o_to_keep_the_point_a_ray_shows():
    network, rays = sure_empty_network(), ray_batch(64)
    # every ray shows a thin wall at x = 4.5 (a sliver of bin 4 of 8)
    samples = same_on_every_ray([0.5, 4.45], [1.0, 4.55], 64)
    weights = torch.tensor([0.0, 0.95]).repeat(64)
    online = OnlineOccupancy(network, 0.9, surface_points=True)
    wall = online.shown_points(samples, weights, rays)
    assert len(wall) == 64 and not network.occupied(wall, 0.9).any()
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-2)
    for _ in range(60):
        loss = online.point_loss(samples, weights, rays)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert network.occupied(wall, 0.9).float().mean() >= 0.9


def test_a_leco_run_with_surface_points_trains_and_adds_the_point_loss(
    tiny_scene, tmp_path, monkeypatch
):
    # a smoke model ten steps in is nowhere opaque: every ray with foreground teaches its point
    monkeypatch.setattr(online_module, "SHOWN_OPACITY", 0.0)
    first = {}
    for points in (False, True):
        losses = online_losses(
            tiny_scene,
            tmp_path / f"run-{points}",
            {
                "occupancy.steps": 10,
                "main_steps": 6,
                "guided.online": True,
                "guided.online_warmup": 2,
                "guided.online_surface_points": points,
            },
        )
        assert list(losses) == [3, 4, 5, 6]
        assert all(torch.isfinite(torch.tensor(x)) for x in losses.values())
        first[points] = losses[3]
    # same seed: the first step O learns on is the same step, and the point loss adds to it
    assert first[True] > first[False]


def test_matter_points_are_the_samples_that_stop_light_where_the_ray_still_sees():
    # ray 0 grazes a crown's top (alpha 0.2 at 2.5, holding 0.2 of its weight: under the bin's
    # surface share only if the top were thinner) then hits the ground at 6.25 (alpha 0.9 of the
    # 0.8 left); ray 1 is clear but for a wisp (alpha 0.02, under online_surface's 0.05)
    rays = ray_batch(2)
    samples = PackedSamples(
        torch.tensor([0.5, 2.25, 6.0, 7.0, 0.5, 3.0]),
        torch.tensor([1.0, 2.75, 6.5, 7.5, 1.0, 3.5]),
        torch.tensor([0, 0, 0, 0, 1, 1]),
    )
    # weights w_i = T_i * alpha_i with T_i = 1 - the weight in front
    weights = torch.tensor([0.0, 0.2, 0.72, 0.05, 0.0, 0.02])
    online = OnlineOccupancy(OccupancyNetwork(2, 16, 4), 0.9, 0.05, dense_points=True)
    points = online.matter_points(samples, weights, rays)
    # the crown (T 1.0, alpha 0.2) and the ground (T 0.8, alpha 0.9); the sample behind the ground
    # (T 0.08) teaches nothing, nor does the wisp
    expected = torch.stack([rays.directions[0] * 2.5, rays.directions[0] * 6.25])
    assert points.shape == (2, 3) and torch.allclose(points, expected)


def test_dense_points_teach_o_to_keep_a_top_the_ray_only_grazes():
    network, rays = sure_empty_network(), ray_batch(64)
    # every ray grazes a top at x = 2.5 (0.3 of its weight) on its way to the ground at x = 6.5,
    # which it shows most
    samples = same_on_every_ray([2.45, 6.45], [2.55, 6.55], 64)
    weights = torch.tensor([0.3, 0.65]).repeat(64)
    top = rays.origins + rays.directions * 2.5
    ground = rays.origins + rays.directions * 6.5
    # the air around them, which the free bins teach O to drop
    air = torch.cat([rays.origins + rays.directions * x for x in (0.5, 1.5, 3.5, 4.5, 5.5)])
    kept = {}
    for dense in (False, True):
        trained = OccupancyNetwork(num_scene_experts=2, width=32, xyz_frequencies=4)
        trained.load_state_dict(network.state_dict())
        online = OnlineOccupancy(trained, 0.9, 0.05, surface_points=True, dense_points=dense)
        optimizer = torch.optim.Adam(trained.parameters(), lr=1e-2)
        for _ in range(100):
            free = trained.decision_logit(trained(air), 0.9)
            loss = online.point_loss(samples, weights, rays)
            loss = loss + F.binary_cross_entropy_with_logits(free, torch.zeros_like(free))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        kept[dense] = [float(trained.occupied(p, 0.9).float().mean()) for p in (top, ground, air)]
    # the shown points alone teach the ground and not the top; with the dense points, both; the
    # air is dropped either way
    assert kept[False][1] >= 0.9 and kept[False][0] < 0.5 and kept[False][2] < 0.1, kept
    assert kept[True][0] >= 0.9 and kept[True][1] >= 0.9 and kept[True][2] < 0.1, kept


BOX = torch.tensor([[0.0, -1.0, -1.0], [8.0, 1.0, 1.0]])


def test_box_points_are_labelled_by_the_fields_alpha_over_one_step():
    # a slab the field holds at density 50, and a faint one at 0.05: over one step of the box's
    # diagonal / 256 (about 0.034), alphas of about 0.82 and 0.0017 against the bound of 0.01
    online = OnlineOccupancy(
        OccupancyNetwork(2, 16, 4), 0.9, box=BOX, box_points=4096, box_alpha=0.01
    )
    field = lambda x: slab_density(x, [WALL]) + 0.05  # noqa: E731
    points, target = online.box_targets(field, Noise(torch.Generator().manual_seed(0)))
    assert points.shape == (4096, 3)
    assert ((points >= BOX[0]) & (points <= BOX[1])).all()
    inside = (points[:, 0] > WALL[0]) & (points[:, 0] < WALL[1])
    assert torch.equal(target.bool(), inside)
    assert 0.05 < float(inside.float().mean()) < 0.1  # the wall is 0.6 of the box's 8


def test_box_points_teach_o_a_wall_no_ray_sampled():
    # O starts sure that everything is empty and no render teaches it: the field's density over
    # the box alone makes it keep the wall and drop the air
    network = sure_empty_network()
    online = OnlineOccupancy(network, 0.9, box=BOX, box_points=1024)
    field = lambda x: slab_density(x, [WALL])  # noqa: E731
    noise = Noise(torch.Generator().manual_seed(0))
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-2)
    for _ in range(200):
        loss = online.box_loss(field, noise)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    line = lambda lo, hi: torch.stack(  # noqa: E731
        [torch.linspace(lo, hi, 50), torch.zeros(50), torch.zeros(50)], -1
    )
    assert network.occupied(line(WALL[0] + 0.05, WALL[1] - 0.05), 0.9).float().mean() >= 0.9
    assert network.occupied(line(0.5, 3.5), 0.9).float().mean() <= 0.05


def test_box_points_need_the_box():
    with pytest.raises(ValueError, match="box_points needs the scene's box"):
        OnlineOccupancy(OccupancyNetwork(2, 16, 4), 0.9, box_points=16)


@pytest.mark.parametrize("method, section", [("leco", ""), ("ngp-leco", "ngp_leco.")])
def test_a_run_with_box_points_adds_their_loss_and_charges_them(
    tiny_scene, tmp_path, method, section
):
    charged, first = {}, {}
    for points in (0, 512):
        run = tmp_path / f"{method}-{points}"
        cfg = TrainConfig(
            method=method,
            profile="smoke",
            metrics_every=1,
            seed=0,
            overrides={
                f"{section}occupancy.steps": 10,
                "main_steps": 4,
                f"{section}guided.online": True,
                f"{section}guided.online_warmup": 1,
                f"{section}guided.online_box_points": points,
            },
        )
        run_training(cfg, tiny_scene.root, run, backend="local")
        rows = [r for r in read_metrics(run / "metrics.jsonl") if r["phase"] == "main"]
        losses = [r["occupancy_online_loss"] for r in rows if "occupancy_online_loss" in r]
        assert len(losses) == 3 and all(torch.isfinite(torch.tensor(losses)))
        first[points] = losses[0]
        charged[points] = rows[1]["samples_per_ray"]
    assert first[512] > first[0]  # same seed, same step: the box loss adds to the bins' loss
    rays = TrainConfig(method=method, profile="smoke").resolved_profile().rays_per_device
    assert charged[512] - charged[0] == pytest.approx(512 / rays, rel=0.05)


@pytest.mark.parametrize(
    "method, section", [("leco", ""), ("ngp-leco", "ngp_leco."), ("leco-prop", "leco_prop.")]
)
def test_a_run_with_free_error_labels_fewer_bins_free(tiny_scene, tmp_path, method, section):
    # the same seed and steps: with a bound no early ray renders within, the rays' free labels go
    # and the online loss is another number (finite)
    first = {}
    for bound in (0.0, 1e-6):
        run = tmp_path / f"{method}-{bound}"
        cfg = TrainConfig(
            method=method,
            profile="smoke",
            metrics_every=1,
            seed=0,
            overrides={
                f"{section}occupancy.steps": 10,
                "main_steps": 4,
                f"{section}guided.online": True,
                f"{section}guided.online_warmup": 1,
                f"{section}guided.online_free_error": bound,
            },
        )
        run_training(cfg, tiny_scene.root, run, backend="local")
        rows = [r for r in read_metrics(run / "metrics.jsonl") if r["phase"] == "main"]
        losses = [r["occupancy_online_loss"] for r in rows if "occupancy_online_loss" in r]
        assert len(losses) == 3 and all(torch.isfinite(torch.tensor(losses)))
        first[bound] = losses[0]
    assert first[1e-6] != pytest.approx(first[0.0], rel=1e-3)
