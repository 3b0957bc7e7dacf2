"""Parameter counts of the networks in model/fields, from a profile's numbers alone (no torch).

The API checks a job's memory before accepting it and must not load PyTorch to do so; these formulas
follow the layer lists in model/fields, and tests/model/test_sizes.py holds them equal to the counts
of networks built on PyTorch's meta device for every profile and the settings that change a
network's shape."""

from __future__ import annotations

import math

from model.profiles import Profile

BACKGROUND_FREQUENCIES = 10  # model/fields/background.py's point encoding
# What a GPU rank's ray sampler keeps on the device for each training pixel (model/scenes/rays.py):
# its uint8 colour and its int32 place in the epoch's order
RESIDENT_BYTES_PER_PIXEL = 3 + 4


def keeps_pixels_on_device(pixels: int, max_mb: float) -> bool:
    """Whether a GPU rank keeps a training split of `pixels` pixels on the device (every rank draws
    from all of them): while they take at most `pixels_on_device_max_mb`; else its batches are
    prefetched from the host (workers/train/ray_batches.py)."""
    return pixels * RESIDENT_BYTES_PER_PIXEL <= max_mb * 2**20


def resident_pixel_bytes(pixels: int, max_mb: float) -> int:
    """Device bytes a GPU rank holds for its training split's pixels (none when prefetched)."""
    return pixels * RESIDENT_BYTES_PER_PIXEL if keeps_pixels_on_device(pixels, max_mb) else 0


def linear(inputs: int, outputs: int, bias: bool = True) -> int:
    return inputs * outputs + (outputs if bias else 0)


def encoded(frequencies: int, in_dim: int = 3) -> int:
    """FrequencyEncoding.out_dim: the raw input plus a sin and a cos per frequency."""
    return in_dim * (1 + 2 * frequencies)


def expert(width: int, layers: int) -> int:
    return layers * linear(width, width)


def scene_head(width: int, dir_dim: int, appearance_dim: int) -> int:
    colour = linear(width + dir_dim + appearance_dim, width // 2) + linear(width // 2, 3)
    return linear(width, 1) + linear(width, width) + colour


def switch_nerf(profile: Profile, num_images: int) -> int:
    n = profile.network
    gate = 2 * linear(n.width, n.width) + 2 * n.width + linear(n.width, n.num_experts, bias=False)
    return (
        num_images * n.appearance_dim
        + linear(encoded(n.xyz_frequencies), n.width)
        + gate
        + n.num_experts * expert(n.width, n.expert_layers)
        + scene_head(n.width, encoded(n.dir_frequencies), n.appearance_dim)
    )


def background(profile: Profile, num_images: int) -> int:
    b, n = profile.background, profile.network
    dims = [encoded(BACKGROUND_FREQUENCIES, in_dim=4)] + [b.width] * b.layers
    trunk = sum(linear(a, c) for a, c in zip(dims[:-1], dims[1:]))
    colour = linear(b.width + encoded(n.dir_frequencies) + n.appearance_dim, b.width // 2) + linear(
        b.width // 2, 3
    )
    return num_images * n.appearance_dim + trunk + linear(b.width, 1) + colour


def occupancy_network(profile: Profile) -> int:
    """O: the shared input layer, its inner layers, LayerNorm and n + 1 gate logits
    (model/fields/hmoe.py)."""
    n, o = profile.network, profile.occupancy
    inner = o.gate_width or n.width
    return (
        linear(encoded(n.xyz_frequencies), n.width)
        + linear(n.width, inner)
        + linear(inner, inner)
        + 2 * inner
        + linear(inner, n.num_experts + 1)
        + (linear(inner, 1) if profile.guided.placement else 0)
    )


def hmoe(profile: Profile, num_images: int) -> int:
    """Phase 1's HMoE: O, the scene experts and head, the empty-space expert and head,
    appearance."""
    n, o = profile.network, profile.occupancy
    empty_layers = n.expert_layers if o.homogeneous else o.empty_expert_layers
    return (
        occupancy_network(profile)
        + num_images * n.appearance_dim
        + n.num_experts * expert(n.width, n.expert_layers)
        + scene_head(n.width, encoded(n.dir_frequencies), n.appearance_dim)
        + expert(n.width, empty_layers)
        + linear(n.width, 1)
        + linear(n.width, 3)
    )


def proposal(width: int, layers: int, xyz_frequencies: int) -> int:
    """One proposal density MLP (model/fields/proposal.py)."""
    return (
        linear(encoded(xyz_frequencies), width)
        + (layers - 1) * linear(width, width)
        + linear(width, 1)
    )


def level_resolutions(levels: int, min_resolution: int, max_resolution: int) -> list[int]:
    """A hash encoding's cells per side at every level, N_l = floor(N_min * b^l) (Instant-NGP's Eq.
    2 and 3)."""
    if levels == 1:
        return [min_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(min_resolution)) / (levels - 1))
    return [int(math.floor(min_resolution * growth**level)) for level in range(levels)]


def level_sizes(resolutions: list[int], table_size: int) -> list[int]:
    """Entries of each level's table: its corners when they fit, else the hash table's T."""
    return [min((n + 1) ** 3, table_size) for n in resolutions]


NGP_GEOMETRY_FEATURES, NGP_SH = 15, 16  # model/fields/ngp.py


def hash_field(
    levels: int, features: int, log2_table: int, low: int, high: int, width: int, appearance: int
) -> int:
    """One HashField (model/fields/ngp.py) without its appearance table: the hash tables, the
    density MLP (one hidden layer) and the colour MLP (two), all without biases."""
    table = features * sum(level_sizes(level_resolutions(levels, low, high), 2**log2_table))
    density = linear(levels * features, width, False) + linear(
        width, 1 + NGP_GEOMETRY_FEATURES, False
    )
    colour_in = NGP_GEOMETRY_FEATURES + NGP_SH + appearance
    colour = linear(colour_in, width, False) + linear(width, width, False) + linear(width, 3, False)
    return table + density + colour


def ngp_field(profile: Profile, num_images: int) -> int:
    g, a = profile.ngp, profile.network.appearance_dim
    body = hash_field(
        g.levels, g.features, g.log2_table_size, g.min_resolution, g.max_resolution, g.width, a
    )
    return num_images * a + body


def ngp_background(profile: Profile, num_images: int) -> int:
    g, a = profile.ngp, profile.network.appearance_dim
    if g.background == "mlp":
        return background(profile, num_images)
    top = max(g.background_max_resolution, g.min_resolution)
    body = hash_field(
        g.background_levels,
        g.features,
        g.background_log2_table_size,
        g.min_resolution,
        top,
        g.width,
        a,
    )
    return num_images * a + body
