"""A job's peak training memory per rank, estimated before it runs (issue 17), so the API can refuse a job that
cannot fit where it would run instead of letting a worker be OOM-killed. The networks are built on PyTorch's
meta device (shapes only, no storage), so the estimate costs nothing whatever sizes a request asks for.
Activations use the bytes autograd keeps per main-network sample, which matches the measured
`activation_memory_mb` of the `cpu` profile within 5% for vanilla Switch-NeRF (98 estimated vs 103 MB); a
validation render holds a chunk of rays' samples at once without gradient, which is what sets a small run's
peak. Against measured peak RSS on the city (`cpu`, docs/BENCHMARKS.md): vanilla 1,340 MiB estimated vs
1,507-1,529 measured, LeCO 1,123 vs 849-1,085, the grid 2,393 vs 1,133 (its bound keeps every march step)."""

from __future__ import annotations

import torch

from model.model_info import background, count, hmoe, switch_nerf
from model.profiles import Profile

BYTES_PER_PARAMETER = 16  # fp32 weights, gradients and Adam's two moments
FROZEN_BYTES_PER_PARAMETER = 4  # LeCO's frozen occupancy network in the main phase
RUNTIME_BYTES = 700 * 2**20  # the process itself (Python, torch, rays tables of a `cpu`-size scene): measured
EVAL_CHUNK = 4096  # rays per forward pass of a validation render (workers/validation.py CHUNK)


def saved_bytes_per_sample(width: int, layers: int) -> int:
    """What backward keeps for one sample through an expert network: each layer's input and ReLU mask, the
    input layer, gate and heads (about six more width-sized tensors), and the encodings."""
    return 4 * ((2 * layers + 6) * width + 100)


def live_bytes_per_sample(width: int) -> int:
    """What a forward pass without gradient holds for one sample at its widest point."""
    return 4 * (5 * width + 100)


def main_samples_bound(method: str, profile: Profile) -> int:
    """The most main-network samples with gradient one ray can have."""
    if method == "switch":
        return profile.vanilla.coarse_samples + profile.vanilla.fine_samples + 1
    if method == "grid":
        return profile.grid.march_steps
    return profile.guided.coarse_samples * profile.guided.split


def estimate_peak_bytes(method: str, profile: Profile, num_images: int) -> dict:
    """Per-rank peak bytes and its parts (each naming the settings that drive it)."""
    n, b = profile.network, profile.background
    with torch.device("meta"):
        behind_params = count(background(profile, num_images))
        main = count(switch_nerf(profile, num_images)) + behind_params
        phase1 = occupancy = 0
        if method == "leco":
            occ = hmoe(profile, num_images)
            phase1, occupancy = count(occ) + behind_params, count(occ.gate)
    per_sample = saved_bytes_per_sample(n.width, n.expert_layers)
    behind = profile.rays_per_device * b.samples * 4 * (2 * b.layers * b.width + 100)
    main_act = profile.rays_per_device * main_samples_bound(method, profile) * per_sample + behind
    phase1_act = profile.rays_per_device * profile.occupancy.samples_per_ray * per_sample + behind if phase1 else 0
    render = EVAL_CHUNK * max(main_samples_bound(method, profile), profile.occupancy.samples_per_ray if phase1
                              else 0) * live_bytes_per_sample(n.width)
    parts = {
        "parameters": max(main * BYTES_PER_PARAMETER + occupancy * FROZEN_BYTES_PER_PARAMETER,
                          phase1 * BYTES_PER_PARAMETER),
        "activations": max(main_act, phase1_act, render),
        "grid": 5 * profile.grid.resolution**3 if method == "grid" else 0,  # float values + occupied bits
        "runtime": RUNTIME_BYTES,
    }
    return {"parts": parts, "total": sum(parts.values()), "parameters": max(main, phase1),
            "training_activations": max(main_act, phase1_act)}


DRIVERS = {
    "parameters": "network.width, network.num_experts, network.expert_layers, network.appearance_dim",
    "activations": "rays_per_device (or a validation render's 4,096 rays) x samples per ray (vanilla.*_samples, guided.coarse_samples x guided.split, "
                   "grid.march_steps, occupancy.samples_per_ray) x network.width x network.expert_layers",
    "grid": "grid.resolution",
}


def describe(estimate: dict) -> str:
    gib = lambda x: f"{x / 2**30:.2f} GiB"
    parts = sorted(((v, k) for k, v in estimate["parts"].items() if k in DRIVERS and v), reverse=True)
    return "; ".join(f"{k} {gib(v)} ({DRIVERS[k]})" for v, k in parts)
