"""The API's memory estimate against what a real step keeps, and its cost whatever the sizes."""

import time

import torch

from model.memory_estimate import estimate_peak_bytes
from model.methods.main_phase import main_loss, render_vanilla
from model.model_info import background, switch_nerf
from model.scenes.rays import RayBatch
from workers.config import TrainConfig
from workers.memory import SavedTensorBytes


def random_rays(n: int, seed: int = 0) -> RayBatch:
    g = torch.Generator().manual_seed(seed)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return RayBatch(
        torch.zeros(n, 3),
        dirs,
        torch.full((n,), 0.1),
        torch.full((n,), 1.5),
        torch.zeros(n, dtype=torch.long),
        torch.rand(n, 3, generator=g),
        torch.arange(n),
    )


def test_the_estimate_of_a_steps_activations_is_within_15_percent_of_what_autograd_keeps():
    torch.manual_seed(0)
    profile = TrainConfig(method="switch", profile="cpu").resolved_profile()
    field, behind = switch_nerf(profile, 10), background(profile, 10)
    with SavedTensorBytes() as saved:
        loss, _ = main_loss(
            render_vanilla(
                field,
                behind,
                random_rays(profile.rays_per_device),
                profile,
                torch.Generator().manual_seed(0),
            ),
            random_rays(profile.rays_per_device),
            5e-4,
        )
    weights = sum(p.numel() * 4 for m in (field, behind) for p in m.parameters())
    # the hook also sees the weights (saved by the matmuls)
    kept = saved.megabytes * 2**20 - weights
    estimated = estimate_peak_bytes("switch", profile, 10)["training_activations"]
    assert 0.85 < estimated / kept < 1.15, (estimated / 2**20, kept / 2**20)


def test_the_estimate_builds_nothing_real_however_large_the_request():
    profile = TrainConfig(
        method="leco",
        profile="paper",
        overrides={"network.width": 2048, "network.num_experts": 64, "network.expert_layers": 16},
    ).resolved_profile()
    started = time.perf_counter()
    estimate = estimate_peak_bytes("leco", profile, 5000)
    assert time.perf_counter() - started < 5.0
    # weights, grads, Adam
    assert estimate["parameters"] > 4e9 and estimate["parts"]["parameters"] > 60 * 2**30
