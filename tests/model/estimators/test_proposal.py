"""S+Prop: proposal networks sized to LeCO's O, inverse-CDF resampling level by level, the
interlevel loss against the main network's detached weights, the anneal and the update schedule."""

import pytest
import torch

from model import sizes
from model.estimators.proposal import (
    UpdateSchedule,
    anneal_power,
    interlevel_loss,
    outer_weights,
    pdf_edges,
)
from model.fields.proposal import ProposalDensity
from model.methods import get_method
from model.methods.base import Step
from model.methods.costs import proposal_width
from model.methods.parts import read_parts
from model.model_info import model_info
from model.profiles import get_profile
from model.render.noise import Noise
from model.scenes.rays import RayBatch


@pytest.mark.parametrize(
    "profile,expected,o", [("cpu", 13_888, 13_962), ("paper", 153_760, 153_865)]
)
def test_proposals_total_the_parameters_of_lecos_occupancy_network(profile, expected, o):
    p = get_profile(profile)
    assert sizes.occupancy_network(p) == o
    assert model_info("prop", p)["components"]["proposal_networks"] == expected
    width = proposal_width(p)
    built = ProposalDensity(width, p.prop.layers, p.network.xyz_frequencies)
    assert sum(x.numel() for x in built.parameters()) * len(p.prop.samples) == expected
    assert len(p.prop.samples) * sizes.proposal(width + 1, p.prop.layers, 12) > o  # the widest fit


def test_pdf_edges_follow_the_histogram_and_stay_sorted_inside_it():
    edges = torch.linspace(0.0, 4.0, 5).expand(3, 5).contiguous()  # bins [0,1) [1,2) [2,3) [3,4)
    weights = torch.tensor([[0.0, 1.0, 0.0, 0.0]]).expand(3, 4)
    out = pdf_edges(edges, weights, 64, Noise(torch.Generator().manual_seed(0)), padding=0.0)
    assert out.shape == (3, 65) and (out[:, 1:] >= out[:, :-1]).all()
    assert ((out >= 1.0) & (out <= 2.0)).all()  # every new interval inside the only bin with weight
    # weights^0: the anneal's start
    uniform = pdf_edges(edges, weights, 64, None, anneal=0.0, padding=0.0)
    assert torch.allclose(uniform[0], torch.linspace(0.0, 4.0, 65), atol=1e-5)
    # weights + 1 = (1, 2, 1, 1): a fifth in [0, 1)
    padded = pdf_edges(edges, weights, 64, None, padding=1.0)
    assert int((padded[0] < 1.0).sum()) == 13  # the edge at 0 and 64 / 5 more


def test_pdf_edges_of_a_ray_with_no_weight_are_uniform_not_nan():
    # A ray that misses the box has an all-zero weight row; without padding the CDF was 0 / 0.
    edges = torch.linspace(0.0, 4.0, 5).expand(2, 5).contiguous()
    weights = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 3.0, 1.0, 0.0]])
    out = pdf_edges(edges, weights, 8, None, padding=0.0)
    assert torch.isfinite(out).all()
    assert torch.allclose(out[0], torch.linspace(0.0, 4.0, 9), atol=1e-5)
    # the CDF ends at exactly 1
    assert out[1, 0] == pytest.approx(1.0) and out[1, -1] == pytest.approx(3.0)
    assert float(out[1, 6]) == pytest.approx(2.0, abs=1e-5)  # 3/4 of the mass lies in [1, 2)


def test_outer_weights_bound_the_histogram_and_the_loss_vanishes_when_it_does():
    g = torch.Generator().manual_seed(1)
    source = torch.sort(torch.rand(4, 9, generator=g) * 10, -1).values
    source[:, 0], source[:, -1] = 0.0, 10.0
    source_w = torch.rand(4, 8, generator=g)
    target = torch.sort(torch.rand(4, 17, generator=g) * 8 + 1, -1).values
    outer = outer_weights(target, source, source_w)
    # Brute force: every source interval overlapping the target interval counts.
    for r in range(4):
        for j in range(16):
            overlap = (source[r, :-1] < target[r, j + 1]) & (source[r, 1:] > target[r, j])
            assert outer[r, j] == pytest.approx(float(source_w[r][overlap].sum()), abs=1e-5)
    main_w = torch.rand(4, 16, generator=g) * 0.1
    # already an upper bound
    assert float(interlevel_loss(target, main_w, [(target, main_w * 1.5)])) == 0.0
    assert float(interlevel_loss(target, main_w, [(target, main_w * 0.5)])) > 0.0


def test_interlevel_loss_trains_the_proposals_and_never_the_main_weights():
    main_w = torch.full((2, 4), 0.2, requires_grad=True)
    proposal_w = torch.full((2, 4), 0.05, requires_grad=True)
    edges = torch.linspace(0, 1, 5).expand(2, 5)
    interlevel_loss(edges, main_w, [(edges, proposal_w)]).backward()
    assert main_w.grad is None and (proposal_w.grad < 0).all()  # raise the proposal's histogram


def test_anneal_and_update_schedule_follow_nerfstudio_and_nerfacc():
    assert anneal_power(0, 1000, 10.0) == 0.0 and anneal_power(1000, 1000, 10.0) == 1.0
    assert anneal_power(100, 1000, 10.0) == pytest.approx(10 * 0.1 / (9 * 0.1 + 1))
    assert anneal_power(None, 1000, 10.0) == 1.0
    schedule = UpdateSchedule(every=5, warmup=100)
    due = [step for step in range(300) if schedule.due(step)]
    assert due[:3] == [0, 1, 2]  # every step at first
    late = [s for s in due if s >= 150]
    assert all(b - a == 5 for a, b in zip(late, late[1:]))  # then every 5th


def test_a_prop_step_samples_main_samples_per_ray_and_learns_only_when_due(tiny_scene):
    profile = get_profile("smoke")
    method = get_method("prop")(profile)
    torch.manual_seed(0)
    models = method.build(tiny_scene.num_images, tiny_scene.bounds.aabb)
    from model.scenes import RaySampler

    rays: RayBatch = RaySampler(tiny_scene.train, tiny_scene.bounds.aabb, 64, 0, 0, 1).next()
    g = torch.Generator().manual_seed(0)
    loss, parts = method.step(models, Step("main", rays, Noise(g), 0.0, 0, seed=0))
    loss.backward()
    parts = read_parts(parts)
    # Every ray that crosses the box gets exactly main_samples; the ones that miss it (7 of these
    # 64) get none.
    hits = int((rays.far > rays.near).sum())
    assert 0 < hits < len(rays)
    assert (
        parts["samples_per_hit_ray"] == profile.prop.main_samples and parts["interlevel_loss"] >= 0
    )
    assert parts["samples_per_ray"] == pytest.approx(profile.prop.main_samples * hits / len(rays))
    assert all(p.grad is not None for p in models.proposals.parameters())
    models.zero_grad(set_to_none=True)
    method.schedule.since_update = -10  # not due on the next step
    loss, parts = method.step(models, Step("main", rays, Noise(g), 0.0, 11, seed=0))
    loss.backward()
    assert "interlevel_loss" not in parts and all(
        p.grad is None for p in models.proposals.parameters()
    )
    occupied = method.final_occupancy(models)(torch.rand(100, 3) * 2 - 1)
    assert occupied.dtype == torch.bool and occupied.shape == (100,)


def test_the_interlevel_loss_over_chosen_rows_is_the_loss_of_those_rows_alone():
    g = torch.Generator().manual_seed(3)
    edges = torch.sort(torch.rand(6, 9, generator=g), -1).values
    main_w = torch.rand(6, 8, generator=g) * 0.2
    level = (edges, torch.rand(6, 8, generator=g) * 0.1)
    rows = torch.tensor([True, False, True, True, False, True])
    alone = interlevel_loss(edges[rows], main_w[rows], [(level[0][rows], level[1][rows])])
    assert float(interlevel_loss(edges, main_w, [level], rows)) == pytest.approx(float(alone))
    none = torch.zeros(6, dtype=torch.bool)
    assert float(interlevel_loss(edges, main_w, [level], none)) == 0.0


def static(name: str, on: bool):
    from workers.config import TrainConfig

    return TrainConfig(
        method=name, profile="smoke", overrides={"prop.static_shapes": on}
    ).resolved_profile()


def batch(tiny_scene, seed: int) -> RayBatch:
    from model.scenes import RaySampler

    return RaySampler(tiny_scene.train, tiny_scene.bounds.aabb, 64, seed, 0, 1).next()


@pytest.mark.parametrize("name", ["prop", "ngp-prop"])
def test_static_shapes_render_every_ray_as_picking_out_the_hits_does(tiny_scene, name):
    rays = batch(tiny_scene, 0)
    assert 0 < int((rays.far > rays.near).sum()) < len(rays)  # 7 of the 64 miss the box
    renders = []
    for on in (False, True):
        method = get_method(name)(static(name, on))
        torch.manual_seed(0)
        models = method.build(tiny_scene.num_images, tiny_scene.bounds.aabb).eval()  # no noise
        with torch.no_grad():
            renders.append(method.render_main(models, rays, None, None).rendered)
    picked, padded = renders
    for field in ("rgb", "depth", "opacity", "transmittance"):
        assert torch.allclose(getattr(padded, field), getattr(picked, field), atol=1e-6), field
    # a miss's intervals are empty: its weights are zero and it shows its background alone
    miss = rays.far <= rays.near
    assert padded.weights.shape == (len(rays), picked.weights.shape[1])
    assert float(padded.weights[miss].abs().max()) == 0.0


def test_a_static_ngp_prop_step_has_fixed_shapes_and_reads_nothing_from_the_device(tiny_scene):
    from torch.profiler import profile as torch_profile

    from model.methods.stages import HOST_READ

    method = get_method("ngp-prop")(static("ngp-prop", True))
    torch.manual_seed(0)
    models = method.build(tiny_scene.num_images, tiny_scene.bounds.aabb)
    shapes = []
    models.field.register_forward_hook(lambda m, args, out: shapes.append(args[0].shape))
    g = torch.Generator().manual_seed(0)
    reads = {"aten::nonzero", "aten::_local_scalar_dense", "aten::masked_select", HOST_READ}
    for seed in (0, 1):
        rays = batch(tiny_scene, seed)
        with torch_profile() as prof:
            loss, parts = method.step(models, Step("main", rays, Noise(g), 0.5, 0, seed=0))
            loss.backward()
        assert not reads & {e.name for e in prof.events()}
        assert "interlevel_loss" in parts
    hits = [int((batch(tiny_scene, s).far > batch(tiny_scene, s).near).sum()) for s in (0, 1)]
    assert hits[0] != hits[1] and shapes[0] == shapes[1]  # other hits, the same shapes
