"""The API's memory estimate against what a real step keeps, and its cost whatever the sizes."""

import time

import pytest
import torch

from model.memory_estimate import estimate_peak_bytes
from model.methods import METHODS, get_method
from model.methods.base import Step
from model.methods.main_phase import main_loss, render_vanilla
from model.model_info import background, switch_nerf
from model.render.noise import Noise
from model.scenes.rays import PixelTable, RayBatch
from workers.config import TrainConfig
from workers.memory import SavedTensorBytes
from workers.models import build_models


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
                Noise(torch.Generator().manual_seed(0)),
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


# A marching sampler's grid starts with every cell occupied and drops those an update finds under
# its threshold: with the threshold at almost nothing, every march step of a ray in the box is
# sampled, the most the grid can give (what the estimate counts). A coarse grid updates in a
# fraction of the time and marches the same steps.
WORST_CASE = {
    "grid": {"grid.threshold": 1e-12, "grid.resolution": 32},
    "ngp": {"ngp.grid.threshold": 1e-12, "ngp.grid.resolution": 32},
}


def activation_bytes(method, models, phase: str, rays: RayBatch, steps: list[int]) -> int:
    """The most bytes autograd keeps over these steps of a phase, the weights left out."""
    weights = {p.untyped_storage().data_ptr() for p in models.parameters()}
    most = 0
    for k in steps:
        with SavedTensorBytes() as saved:
            method.step(
                models, Step(phase, rays, Noise(torch.Generator().manual_seed(k)), 0.5, k, 0)
            )
        most = max(most, sum(n for ptr, n in saved.storages.items() if ptr not in weights))
    return most


# every method at its defaults, and O asked at eight points of each bin (its queries keep their
# activations while it learns online and places samples)
CASES = [pytest.param(name, {}, id=name) for name in METHODS] + [
    pytest.param("leco", {"guided.queries_per_bin": 8}, id="leco-8-queries-a-bin")
]


@pytest.mark.parametrize("name, overrides", CASES)
def test_each_phases_estimate_is_within_25_percent_of_what_its_worst_step_keeps(
    name, overrides, tiny_scene
):
    """Every method's memory model against what autograd keeps in the worst step of each phase
    (early steps, where proposals learn every step, and late ones, past O's online warm-up and over
    the proposals' period), at two batch sizes of the `cpu` profile on the tiny city. The estimate
    is given the rays' mean length in the box, which a march's samples scale with."""
    table, aabb = PixelTable(tiny_scene.train), tiny_scene.bounds.aabb
    diagonal = float((aabb[1] - aabb[0]).norm())
    for rays_per_device in (96, 384):
        profile = TrainConfig(
            method=name,
            profile="cpu",
            overrides={
                "rays_per_device": rays_per_device,
                **WORST_CASE.get(name, {}),
                **overrides,
            },
        ).resolved_profile()
        method = get_method(name)(profile)
        models = build_models(method, tiny_scene.num_images, aabb, 0)
        pixels = torch.randint(
            0, len(table), (rays_per_device,), generator=torch.Generator().manual_seed(0)
        )
        rays = table.rays(pixels, aabb)
        inside = float((rays.far - rays.near).clamp(min=0).mean()) / diagonal
        estimate = estimate_peak_bytes(name, profile, tiny_scene.num_images, inside)
        for phase in method.phases:
            method.start_phase(models, phase, True, torch.device("cpu"), lambda text: None)
            kept = activation_bytes(
                method, models, phase, rays, [0, 1, 5000, 5001, 5002, 5003, 5004]
            )
            ratio = estimate["training_by_phase"][phase] / kept
            assert 0.8 <= ratio <= 1.25, (rays_per_device, phase, round(ratio, 3))


def test_os_coarse_queries_count_in_leco_s_estimate():
    """The guided sampler asks O about every coarse bin at `queries_per_bin` points, with gradients
    while O learns: 4,096 bins x 16 points x 16,384 rays is tens of GiB, whatever the main
    samples."""
    ask = lambda **o: TrainConfig(
        method="leco",
        profile="cpu",
        overrides={"rays_per_device": 16384, **{f"guided.{k}": v for k, v in o.items()}},
    ).resolved_profile()
    many = estimate_peak_bytes("leco", ask(coarse_samples=4096, queries_per_bin=16), 100)
    few = estimate_peak_bytes("leco", ask(), 100)
    assert many["training_by_phase"]["main"] > 30 * 2**30 > 10 * few["training_by_phase"]["main"]


def test_a_gpu_ranks_resident_pixels_are_a_part_of_the_estimate_up_to_their_bound():
    from model.memory_estimate import describe
    from model.sizes import resident_pixel_bytes

    profile = TrainConfig(method="prop", profile="cpu").resolved_profile()
    # lego at full size: 100 views of 800 x 800, 7 bytes a pixel, under the default 4,096 MB
    pixels = 100 * 800 * 800
    held = resident_pixel_bytes(pixels, 4096)
    assert held == pixels * 7
    without = estimate_peak_bytes("prop", profile, 100)
    with_pixels = estimate_peak_bytes("prop", profile, 100, resident_pixels=held)
    assert with_pixels["total"] - without["total"] == held == with_pixels["parts"]["pixels"]
    assert "pixels 0.42 GiB" in describe(with_pixels) and "pixels" not in describe(without)
    # a split over the bound is prefetched from the host: none of it stays on the device
    assert resident_pixel_bytes(pixels, 400) == 0
