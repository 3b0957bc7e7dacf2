"""A short CPU run of LeCO's occupancy phase on the tiny synthetic city shows the method, not just shapes:
most points go to the empty expert, its points have far lower density, and the learned occupancy keeps the
coarse bins that hold the true surfaces more often than it keeps bins at all."""

import pytest
import torch

from model.fields import HMoE
from model.fields.background import BackgroundField
from model.occupancy import OccupancyPredictor
from model.occupancy_phase import occupancy_step
from model.profiles import OccupancyPhaseConfig
from model.samplers import stratified_edges
from model.scenes import RaySampler, load_scene
from model.scenes.rays import PixelTable
from model.scenes.synthetic import generate

STEPS = 400


def surface_bin_recall(predictor, scene, num_coarse=32):
    """Share of observed surface points (train depth maps) whose coarse bin the predictor keeps, and the
    share of all coarse bins it keeps (the occupancy ratio)."""
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
    cfg = OccupancyPhaseConfig(samples_per_ray=32, steps=STEPS, lr=2e-3, w_g=5e-2)  # the cpu profile's w_g
    optimizer = torch.optim.Adam([*model.parameters(), *background.parameters()], lr=cfg.lr)
    sampler = RaySampler(scene.train, scene.bounds.aabb, batch_size=256, seed=0)
    generator = torch.Generator().manual_seed(0)
    for _ in range(STEPS):
        loss, parts = occupancy_step(model, background, sampler.next(), cfg, 8, generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    recall, kept = surface_bin_recall(OccupancyPredictor.from_hmoe(model), scene)
    print(f"after {STEPS} steps: to E_e {parts['fraction_empty']:.3f} (optimum {80 / 88:.3f}), density ratio "
          f"{parts['density_ratio']:.3f}, surface-bin recall {recall:.3f}, kept bins {kept:.3f}")
    assert parts["fraction_empty"] > 0.75
    assert parts["density_ratio"] < 0.5 and parts["alpha_ratio"] < 0.5
    # Better than chance already; "high" recall needs a longer run (tracked in issue 3's note).
    assert kept < 0.3 and recall > kept
