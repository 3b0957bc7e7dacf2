"""The `rays` block of eval.json: what reaches the main network on validation rays, counted alike
for every method, and whether the bin of each ray's visible surface is among it
(workers/train/evaluate.py ray_accounting)."""

import json

import pytest
import torch
from torch import nn

from model.methods import get_method
from model.methods.main_phase import MainRender
from model.render.samples import PackedSamples
from model.render.volume import Rendered
from model.scenes.rays import PixelTable
from workers.config import TrainConfig
from workers.train.evaluate import accounting_pixels, ray_accounting

BINS = 8
CPU = torch.device("cpu")


class SurfaceBinToy:
    """One main sample per surface ray, in the coarse bin `shift` bins past the one holding its
    surface (0: the surface's own bin), with render weight 0.75; rays without a surface get none."""

    def __init__(self, depth: torch.Tensor, shift: int):
        self.depth, self.shift = depth, shift

    def render_main(self, models, rays, noise, phase_step) -> MainRender:
        t = self.depth[rays.pixel].to(rays.near.dtype)
        surface = torch.isfinite(t) & (t >= rays.near) & (t < rays.far) & (rays.far > rays.near)
        span = rays.far - rays.near
        b = (
            ((torch.where(surface, t, rays.near) - rays.near) / span.clamp(min=1e-12) * BINS)
            .floor()
            .long()
        )
        b = (b.clamp(0, BINS - 1) + self.shift) % BINS
        ray = torch.nonzero(surface)[:, 0]
        starts = rays.near[ray] + span[ray] * (b[ray] + 0.25) / BINS
        samples = PackedSamples(starts, starts + span[ray] * 0.5 / BINS, ray)
        n = len(rays)
        weights = torch.full((len(ray),), 0.75)
        rendered = Rendered(
            torch.zeros(n, 3), torch.zeros(n), torch.zeros(n), weights, torch.ones(n)
        )
        return MainRender(rendered, None, len(ray) / n, None, samples=samples)


def truth_counts(views, aabb) -> tuple[int, int, torch.Tensor]:
    """(rays that cross the box, rays whose visible surface lies in it, flat depth), from the views
    directly."""
    rays = PixelTable(views).rays(torch.arange(views.num_pixels), aabb)
    depth = torch.cat([d.reshape(-1) for d in views.depth])
    t = depth.to(rays.near.dtype)
    hit = rays.far > rays.near
    surface = torch.isfinite(t) & (t >= rays.near) & (t < rays.far) & hit
    return int(hit.sum()), int(surface.sum()), depth


def test_every_validation_pixel_when_few_else_a_seeded_subset(tiny_scene):
    views = tiny_scene.splits["val"]
    ids, text = accounting_pixels(views)
    assert (
        torch.equal(ids, torch.arange(2400))
        and text == "all 2,400 pixels of the 2 validation views"
    )
    ids, text = accounting_pixels(views, count=500)
    again, _ = accounting_pixels(views, count=500)
    assert len(ids) == 500 and torch.equal(ids, again) and bool((ids[1:] > ids[:-1]).all())
    assert text == "a seeded subset (seed 0) of 500 of the 2,400 pixels of the 2 validation views"


def test_a_sampler_that_keeps_the_surface_bin_and_one_that_misses_it(tiny_scene):
    views, aabb = tiny_scene.splits["val"], tiny_scene.bounds.aabb
    hits, surfaces, depth = truth_counts(views, aabb)
    assert 2000 < hits <= 2400 and 1000 < surfaces <= hits  # drone views: most rays see the city
    models = nn.Module()
    kept = ray_accounting(
        SurfaceBinToy(depth, 0), models, views, aabb, BINS, CPU, views.depth, "exact depth maps"
    )
    assert kept == {
        "selection": "all 2,400 pixels of the 2 validation views",
        "rays": 2400,
        "bins": BINS,
        "occupancy_ratio": pytest.approx(surfaces / (hits * BINS)),
        "samples_per_hit_ray": pytest.approx(surfaces / hits),
        "hit_ray_fraction": pytest.approx(hits / 2400),
        "depth_source": "exact depth maps",
        "surface_rays": surfaces,
        "surface_bin_kept": 1.0,
        "foreground_opacity": pytest.approx(0.75),
    }
    missed = ray_accounting(
        SurfaceBinToy(depth, 1), models, views, aabb, BINS, CPU, views.depth, "exact depth maps"
    )
    # as many bins, the wrong ones
    assert missed["occupancy_ratio"] == pytest.approx(kept["occupancy_ratio"])
    assert missed["surface_bin_kept"] == 0.0 and missed["surface_rays"] == surfaces
    assert missed["foreground_opacity"] == pytest.approx(0.75)
    assert models.training  # the networks are back in the mode they came in


def test_without_depth_maps_the_block_says_so_and_has_no_surface_figures(tiny_scene):
    views, aabb = tiny_scene.splits["val"], tiny_scene.bounds.aabb
    _, _, depth = truth_counts(views, aabb)
    block = ray_accounting(
        SurfaceBinToy(depth, 0), nn.Module(), views, aabb, BINS, CPU, None, "no depth maps here"
    )
    assert block["depth_source"] is None and block["surface_note"] == "no depth maps here"
    assert (
        "surface_bin_kept" not in block
        and "foreground_opacity" not in block
        and block["occupancy_ratio"] > 0
    )


def test_weights_that_do_not_line_up_drop_the_opacity_only(tiny_scene):
    class Misaligned(SurfaceBinToy):
        def render_main(self, models, rays, noise, phase_step) -> MainRender:
            render = super().render_main(models, rays, noise, phase_step)
            # one short: not the samples' order
            render.rendered.weights = render.rendered.weights[:-1]
            return render

    views, aabb = tiny_scene.splits["val"], tiny_scene.bounds.aabb
    _, surfaces, depth = truth_counts(views, aabb)
    block = ray_accounting(
        Misaligned(depth, 0), nn.Module(), views, aabb, BINS, CPU, views.depth, "exact depth maps"
    )
    assert block["foreground_opacity"] is None and block["surface_bin_kept"] == 1.0
    assert block["surface_rays"] == surfaces


def test_vanilla_switch_nerf_reaches_every_bin_of_every_hit_ray(tiny_scene):
    """The real vanilla sampler (untrained smoke networks): coarse and fine samples on every bin."""
    views, aabb = tiny_scene.splits["val"], tiny_scene.bounds.aabb
    hits, surfaces, _ = truth_counts(views, aabb)
    profile = TrainConfig(method="switch", profile="smoke").resolved_profile()
    method = get_method("switch")(profile)
    torch.manual_seed(0)
    models = method.build(len(tiny_scene.train) + len(views), aabb)
    bins = profile.guided.coarse_samples
    block = ray_accounting(method, models, views, aabb, bins, CPU, views.depth, "exact depth maps")
    # the merged edges' intervals
    per_ray = profile.vanilla.coarse_samples + profile.vanilla.fine_samples
    assert block["occupancy_ratio"] == 1.0 and block["surface_bin_kept"] == 1.0
    assert block["surface_rays"] == surfaces and block["hit_ray_fraction"] == pytest.approx(
        hits / 2400
    )
    # Zero-length intervals of the rays that miss the box are main-network samples too (they cost as
    # much).
    assert block["samples_per_hit_ray"] == pytest.approx(2400 * per_ray / hits)
    assert 0.0 <= block["foreground_opacity"] <= 1.0
    json.dumps(block)  # plain numbers and strings: it goes into eval.json as it is


def test_eval_json_has_the_rays_block_and_scores_the_decision_rules(tiny_scene, tmp_path):
    """A few steps of a LeCO smoke run sampling with a threshold (as the cpu profile does), then the
    final evaluation `leco train` writes: O's top-1 rule is scored beside the threshold, and the
    rays are counted."""
    from workers.train.run import run_training

    overrides = {"occupancy.steps": 3, "main_steps": 3, "guided.empty_threshold": 0.9}
    cfg = TrainConfig(method="leco", profile="smoke", overrides=overrides, val_appearance_steps=0)
    run_training(cfg, tiny_scene.root, tmp_path / "run", backend="local")
    result = json.loads((tmp_path / "run" / "eval.json").read_text())
    rays = result["rays"]
    hits, surfaces, _ = truth_counts(tiny_scene.splits["val"], tiny_scene.bounds.aabb)
    assert rays["selection"] == "all 2,400 pixels of the 2 validation views" and rays["bins"] == 8
    assert rays["depth_source"] == "exact depth maps" and rays["surface_rays"] == surfaces
    assert rays["hit_ray_fraction"] == pytest.approx(hits / 2400)
    # Three steps teach O little: it may still keep every bin, but never more than all of them.
    assert 0.0 < rays["occupancy_ratio"] <= 1.0 and 0.0 <= rays["surface_bin_kept"] <= 1.0
    assert 0.0 <= rays["foreground_opacity"] <= 1.0 and rays["samples_per_hit_ray"] > 0
    occupancy = result["occupancy"]
    assert len(occupancy["layers"]) == 8 and 0.0 <= occupancy["ground_recall"] <= 1.0
    assert occupancy["ground_cells"] > 500 and occupancy["reference"].startswith(
        "exact ground truth"
    )
    assert all(
        0.0 <= occupancy[f"top1_{k}"] <= 1.0 for k in ("recall", "precision", "f1", "ground_recall")
    )
