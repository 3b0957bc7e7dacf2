"""A short CPU run of LeCO's occupancy phase on the tiny synthetic city shows the method, not just
shapes: most points go to the empty expert, its points have far lower density, and the learned
occupancy keeps the coarse bins that hold the true surfaces far more often than it keeps bins at
all, and finds most occupied cells by the paper's protocol."""

import pytest
import torch

from model.estimators.occupancy import OccupancyPredictor
from model.evaluation.occupancy import evaluate_occupancy
from model.fields import HMoE
from model.fields.background import BackgroundField
from model.methods.leco.phase1 import occupancy_step
from model.methods.parts import read_parts
from model.profiles import OccupancyPhaseConfig
from model.render.noise import Noise
from model.render.samples import stratified_edges
from model.scenes import RaySampler, load_scene
from model.scenes.rays import PixelTable
from model.scenes.synthetic import generate

STEPS = 1000


def surface_bin_recall(predictor, scene, num_coarse=32):
    """Share of observed surface points (train depth maps) whose coarse bin the predictor keeps, and
    the share of all coarse bins it keeps (the occupancy ratio)."""
    table = PixelTable(scene.train)
    depth = torch.cat([d.reshape(-1) for d in scene.train.depth])
    ids = torch.nonzero(torch.isfinite(depth)).squeeze(1)
    rays = table.rays(ids, scene.bounds.aabb)
    t = depth[ids]
    ok = (t > rays.near) & (t < rays.far)
    edges = stratified_edges(rays.near[ok], rays.far[ok], num_coarse, None)
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    points = rays.origins[ok][:, None] + rays.directions[ok][:, None] * mids[..., None]
    keep = predictor.occupied(points.reshape(-1, 3)).reshape(mids.shape)
    bins = (torch.searchsorted(edges, t[ok][:, None]).squeeze(1) - 1).clamp(0, num_coarse - 1)
    return float(keep.gather(1, bins[:, None]).float().mean()), float(keep.float().mean())


@pytest.mark.slow
def test_occupancy_phase_learns_sparse_occupancy(tmp_path):
    generate("tiny", 0, tmp_path / "tiny")
    scene = load_scene(tmp_path / "tiny")
    torch.manual_seed(0)
    images = scene.num_images
    model = HMoE(images, width=64, num_scene_experts=8, expert_layers=4)
    background = BackgroundField(images, width=32, layers=2)
    # the cpu profile's w_g
    cfg = OccupancyPhaseConfig(samples_per_ray=32, steps=STEPS, lr=2e-3, w_g=5e-2)
    optimizer = torch.optim.Adam([*model.parameters(), *background.parameters()], lr=cfg.lr)
    sampler = RaySampler(scene.train, scene.bounds.aabb, batch_size=256, seed=0)
    generator = torch.Generator().manual_seed(0)
    for _ in range(STEPS):
        loss, parts = occupancy_step(model, background, sampler.next(), cfg, 8, Noise(generator))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    parts = read_parts(parts)
    predictor = OccupancyPredictor.from_hmoe(model)
    recall, kept = surface_bin_recall(predictor, scene)
    grid = evaluate_occupancy(predictor.occupied, scene.splits["val"], scene.occupancy.aabb, 64)
    print(
        f"after {STEPS} steps: to E_e {parts['fraction_empty']:.3f} (optimum {80 / 88:.3f}), "
        f"density ratio {parts['density_ratio']:.3f}, surface-bin recall {recall:.3f}, kept bins "
        f"{kept:.3f}; paper protocol (64^3): recall {grid['recall']:.3f} precision "
        f"{grid['precision']:.3f} predicted occupied {grid['predicted_occupied_fraction']:.3f}"
    )
    assert parts["fraction_empty"] > 0.8
    assert parts["density_ratio"] < 0.2 and parts["alpha_ratio"] < 0.3
    # The predictor keeps the bins holding true surfaces far more often than bins at large, and its
    # grid recall beats a random grid with as many occupied cells (whose recall is that fraction).
    # Recall is not yet the paper's 0.68-0.96: that comes after 40k steps at width 256; this is 1000
    # steps at width 64.
    assert kept < 0.25 and recall > 2 * kept
    # measured 0.81, 0.17
    assert grid["recall"] > 0.7 and grid["recall"] > 3 * grid["predicted_occupied_fraction"]
