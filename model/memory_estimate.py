"""A job's peak training memory per rank, estimated before it runs, so the API can refuse a job that
cannot fit where it would run instead of letting a worker be OOM-killed. Parameter counts come from
the profile's numbers (model/sizes.py, no PyTorch), so the estimate costs nothing whatever sizes a
request asks for. Activations are the bytes autograd keeps per sample of each network a phase runs
with gradients (the main network's, O's coarse queries, the proposal levels'; a method's memory
model, model/methods/costs.py): within 25% of what the worst step of every phase of every method
keeps, at two batch sizes (tests/model/test_memory_estimate.py). A march's samples scale with the
rays' mean length in the box, which scene info records (`mean_diagonal_fraction`); a validation
render holds a chunk of rays' samples at once without gradient, which is what sets a small run's
peak. `leco bench-memory` sets each method's measured peak RSS beside the total (docs/BENCHMARKS.md
has the numbers)."""

from __future__ import annotations

from model.methods import get_method
from model.methods.costs import PhaseMemory
from model.profiles import Profile

BYTES_PER_PARAMETER = 16  # fp32 weights, gradients and Adam's two moments
FROZEN_BYTES_PER_PARAMETER = 4  # LeCO's frozen occupancy network in the main phase
# the process itself (Python, torch, rays tables of a `cpu`-size scene): measured
RUNTIME_BYTES = 700 * 2**20
EVAL_CHUNK = (
    4096  # rays per forward pass of a validation render (workers/train/validation.py CHUNK)
)


def saved_bytes_per_sample(width: int, layers: int) -> int:
    """What backward keeps for one sample through an expert network: each layer's input and ReLU
    mask, the input layer, gate and heads (about six more width-sized tensors), and the
    encodings."""
    return 4 * ((2 * layers + 6) * width + 100)


def live_bytes_per_sample(width: int) -> int:
    """What a forward pass without gradient holds for one sample at its widest point."""
    return 4 * (5 * width + 100)


def estimate_peak_bytes(
    method: str,
    profile: Profile,
    num_images: int,
    ray_fraction: float = 1.0,
    resident_pixels: int = 0,
) -> dict:
    """Per-rank peak bytes and its parts (each naming the settings that drive it): the worst phase
    of the method's (its registry entry's memory model, model/methods/costs.py) for each part.
    `ray_fraction`: the mean share of the box's diagonal a training ray travels inside the box,
    which a march's samples scale with (1: every ray along the diagonal, the most it can be).
    `resident_pixels`: the bytes a GPU rank keeps of its training pixels (model/sizes.py
    resident_pixel_bytes; 0 on a CPU, whose batches are drawn from the pixel cache)."""
    n, b = profile.network, profile.background
    phases: dict[str, PhaseMemory] = get_method(method).memory(profile, num_images)
    mlp_sample = saved_bytes_per_sample(n.width, n.expert_layers)
    mlp_behind = 4 * (2 * b.layers * b.width + 100)
    rays = profile.rays_per_device
    samples = lambda p: p.samples_per_ray * (ray_fraction if p.marched else 1.0)
    training = {
        k: int(
            rays
            * (
                samples(p) * (p.bytes_per_sample or mlp_sample)
                + p.extra_bytes_per_ray
                + b.samples * (p.background_bytes_per_sample or mlp_behind)
            )
        )
        for k, p in phases.items()
    }
    render = max(
        int(
            EVAL_CHUNK
            * (p.render_samples_per_ray or samples(p))
            * (p.bytes_per_sample or live_bytes_per_sample(n.width))
        )
        for p in phases.values()
    )
    parts = {
        "parameters": max(
            p.trained * BYTES_PER_PARAMETER + p.frozen * FROZEN_BYTES_PER_PARAMETER
            for p in phases.values()
        ),
        "activations": max(max(training.values()), render),
        "estimator": max(p.extra_bytes for p in phases.values()),  # e.g. an occupancy grid's cells
        "pixels": resident_pixels,
        "runtime": RUNTIME_BYTES,
    }
    return {
        "parts": parts,
        "total": sum(parts.values()),
        "parameters": max(p.trained for p in phases.values()),
        "training_activations": max(training.values()),
        "training_by_phase": training,
    }


# A finished run's frames (a render's, an export's views): rendered FRAME_CHUNK rays at a time
# without gradient (workers/render/frames.py CHUNK), with the whole frame's rays, outputs and their
# conversions held at once, and the allocator's growth over a frame's chunks: FRAME_BYTES_PER_PIXEL
# is the most a pixel was measured to cost before the renderer wrote its outputs in place (vanilla's
# 519); since then `leco bench-memory --frames` measures 55-318 over the methods (BENCHMARKS.md).
FRAME_CHUNK = 8192
FRAME_BYTES_PER_PIXEL = 520
# a point cloud's kept points: float64 position, colour, sampling key and order, twice while a
# view's points merge with the kept ones (workers/render/export.py Subsample)
POINT_BYTES = 2 * (24 + 3 + 8 + 8)


def estimate_frames_bytes(
    method: str, profile: Profile, num_images: int, pixels: int, points: int = 0
) -> dict:
    """Peak bytes of rendering frames of `pixels` pixels each with a finished run's networks, as a
    render or an export does, and of keeping `points` points of a point cloud: the weights alone,
    one chunk's samples without gradient, the frame's per-pixel tensors, the points."""
    n = profile.network
    phases: dict[str, PhaseMemory] = get_method(method).memory(profile, num_images)
    chunk = max(
        int(
            FRAME_CHUNK
            * (p.render_samples_per_ray or p.samples_per_ray)
            * (p.bytes_per_sample or live_bytes_per_sample(n.width))
        )
        for p in phases.values()
    )
    parts = {
        "parameters": max(
            (p.trained + p.frozen) * FROZEN_BYTES_PER_PARAMETER for p in phases.values()
        ),
        "activations": chunk,
        "estimator": max(p.extra_bytes for p in phases.values()),
        "frame": pixels * FRAME_BYTES_PER_PIXEL,
        "points": points * POINT_BYTES,
        "runtime": RUNTIME_BYTES,
    }
    return {"parts": parts, "total": sum(parts.values())}


DRIVERS = {
    "parameters": "network.width, network.num_experts, network.expert_layers, "
    "network.appearance_dim; for the hash-grid methods ngp.levels, ngp.log2_table_size, "
    "ngp.features",
    "activations": "rays_per_device (or a validation render's 4,096 rays) x samples per ray "
    "(vanilla.*_samples, guided.main_samples or guided.coarse_samples x guided.split, "
    "grid.march_steps, occupancy.samples_per_ray) x network.width x network.expert_layers "
    "(ngp.levels x ngp.features, ngp.width for the hash-grid methods), O's queries "
    "(guided.coarse_samples x guided.queries_per_bin) and the proposal levels' (prop.samples)",
    "estimator": "grid.resolution (the occupancy grid's cells; ngp.grid.resolution x "
    "ngp.grid.levels for NGP's cascades)",
    "pixels": "a GPU rank's training pixels, 7 bytes each, held on the device up to "
    "pixels_on_device_max_mb",
    "frame": "a frame's pixels: width x height of a render, a view's over stride squared of an "
    "export",
    "points": "an export's max_points (or every kept pixel of every view, when fewer)",
}


def describe(estimate: dict) -> str:
    gib = lambda x: f"{x / 2**30:.2f} GiB"
    parts = sorted(
        ((v, k) for k, v in estimate["parts"].items() if k in DRIVERS and v), reverse=True
    )
    return "; ".join(f"{k} {gib(v)} ({DRIVERS[k]})" for v, k in parts)
