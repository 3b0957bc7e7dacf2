"""What a method costs: each registered method's memory model (PhaseMemory per phase) and the sizes
it derives from, computed from the profile alone (model/sizes.py), so the API can refuse a job that
cannot fit without loading PyTorch; and the sampling budgets `leco bench --sweep` tries
(SweepPoint)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from model import sizes
from model.profiles import GridConfig, Profile


@dataclass(frozen=True)
class PhaseMemory:
    """What one phase of a method keeps per rank, for the memory estimate
    (model/memory_estimate.py)."""

    trained: int  # parameters with gradients and Adam state
    frozen: int = 0  # parameters only read
    samples_per_ray: int = 0  # the most main-size network samples with gradient one ray can have
    render_samples_per_ray: int = 0  # ... in a validation render (no gradient); 0: samples_per_ray
    extra_bytes: int = 0  # state that is neither parameters nor activations (a grid's cells)
    extra_bytes_per_ray: int = 0  # activations of the method's own small networks (proposal MLPs)
    # what backward keeps per main-network sample, and per background sample (0: the Switch-NeRF
    # and MLP-background formulas of model/memory_estimate.py)
    bytes_per_sample: int = 0
    background_bytes_per_sample: int = 0
    # samples_per_ray is a march's steps along the box's diagonal (an occupancy grid with every cell
    # occupied, as it starts): a ray gets them in proportion to its length inside the box
    marched: bool = False


@dataclass(frozen=True)
class SweepPoint:
    """One sampling budget of a method for `leco bench --sweep` (speed against error)."""

    tag: str
    text: str
    overrides: dict = field(default_factory=dict)


def main_phase(profile: Profile, num_images: int, samples_per_ray: int) -> PhaseMemory:
    """The main Switch-NeRF and the background, trained, with `samples_per_ray` main samples per
    ray."""
    trained = sizes.switch_nerf(profile, num_images) + sizes.background(profile, num_images)
    return PhaseMemory(trained=trained, samples_per_ray=samples_per_ray)


def switch(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    v = profile.vanilla
    return {"main": main_phase(profile, num_images, v.coarse_samples + v.fine_samples + 1)}


def leco_main_samples(profile: Profile) -> int:
    """The most main-network samples with gradient one ray can have in LeCO's main phase."""
    g = profile.guided
    return g.main_samples if g.placement else g.coarse_samples * g.split


def occupancy_query_bytes(profile: Profile) -> int:
    """What backward keeps for one query of O (model/fields/hmoe.py OccupancyNetwork): the encoded
    point, the shared input layer's output and, per inner layer, its output, ReLU mask and
    LayerNorm statistics (measured 1,270 bytes at width 64, 1,344 counted)."""
    width, inner = profile.network.width, profile.occupancy.gate_width or profile.network.width
    return 4 * (width + 3 * inner + 80)


def occupancy_queries_per_ray(profile: Profile) -> int:
    """O's queries per ray in the main phase that keep their activations for backward: every
    coarse bin's points (guided.coarse_samples x guided.queries_per_bin) while O learns online or
    places samples (its placement loss); none when O is only read."""
    g = profile.guided
    learns = g.online or g.placement
    return g.coarse_samples * g.queries_per_bin if learns else 0


def leco(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    main = main_phase(profile, num_images, leco_main_samples(profile))
    samples = profile.occupancy.samples_per_ray
    phase1 = sizes.hmoe(profile, num_images) + sizes.background(profile, num_images)
    return {
        "occupancy": PhaseMemory(trained=phase1, samples_per_ray=samples),
        "main": PhaseMemory(
            trained=main.trained,
            frozen=sizes.occupancy_network(profile),
            samples_per_ray=main.samples_per_ray,
            render_samples_per_ray=max(main.samples_per_ray, samples),
            extra_bytes_per_ray=occupancy_queries_per_ray(profile) * occupancy_query_bytes(profile),
        ),
    }


def grid(profile: Profile, num_images: int, g: GridConfig | None = None) -> dict[str, PhaseMemory]:
    g = g or profile.grid
    main = main_phase(profile, num_images, g.march_steps)
    return {
        "main": PhaseMemory(
            main.trained,
            samples_per_ray=main.samples_per_ray,
            # float values + occupied bits
            extra_bytes=5 * g.levels * g.resolution**3,
            marched=True,
        )
    }


def proposal_width(profile: Profile) -> int:
    """`prop.width`, or the widest proposal MLP whose levels together do not exceed LeCO's O's
    parameter count, so the two learned samplers are compared at equal size."""
    p = profile.prop
    if p.width is not None:
        return p.width
    target, levels, f = (
        sizes.occupancy_network(profile),
        len(p.samples),
        profile.network.xyz_frequencies,
    )
    width = 4
    while levels * sizes.proposal(width + 1, p.layers, f) <= target:
        width += 1
    return width


def proposal_parameters(profile: Profile) -> int:
    p = profile.prop
    return len(p.samples) * sizes.proposal(
        proposal_width(profile), p.layers, profile.network.xyz_frequencies
    )


def prop(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    p, width = profile.prop, proposal_width(profile)
    main = main_phase(profile, num_images, p.main_samples)
    # What backward keeps per proposal sample: the encoding and its sines' inputs, each layer's
    # output (its ReLU's, the next layer's input), the density's logit.
    encoded = 3 + 6 * profile.network.xyz_frequencies
    per_ray = sum(p.samples) * 4 * (2 * encoded + p.layers * width + 2)
    return {
        "main": PhaseMemory(
            trained=main.trained + proposal_parameters(profile),
            samples_per_ray=main.samples_per_ray,
            extra_bytes_per_ray=per_ray,
        )
    }


def leco_prop(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    """LeCO's phase 1, then S+Prop's main phase with O beside it, trained while it learns online:
    its queries' activations on top of the proposal levels'."""
    phases, main = leco(profile, num_images), prop(profile, num_images)["main"]
    g = profile.guided
    o_per_ray = (
        g.coarse_samples * g.queries_per_bin * occupancy_query_bytes(profile) if g.online else 0
    )
    o = sizes.occupancy_network(profile)
    phase1 = phases["occupancy"]
    if profile.leco_prop.prop_in_phase1:  # the proposals already learn beside the HMoE
        phase1 = replace(
            phase1,
            trained=phase1.trained + proposal_parameters(profile),
            extra_bytes_per_ray=phase1.extra_bytes_per_ray + main.extra_bytes_per_ray,
        )
    return {
        "occupancy": phase1,
        "main": replace(
            main,
            trained=main.trained + (o if g.online else 0),
            frozen=0 if g.online else o,
            render_samples_per_ray=max(main.samples_per_ray, profile.occupancy.samples_per_ray),
            extra_bytes_per_ray=main.extra_bytes_per_ray + o_per_ray,
        ),
    }


def hash_grid_bytes_per_sample(levels: int, features: int, width: int) -> int:
    """What backward keeps for one sample through a HashField (model/fields/ngp.py): per level its
    corners' rows and trilinear weights and the gathered features, then the MLPs' inputs and
    activations. Fitted to what autograd keeps (2026-11-29, `cpu` profile, per sample at the
    margin): 2,000 bytes at 8 levels, 2 features, width 64; 2,832 at 16 levels; 2,064 at 4
    features; 2,768 at width 128, which this formula gives exactly."""
    return levels * (96 + 4 * features) + 4 * (3 * width + 100)


def on_hash_grids(phases: dict[str, PhaseMemory], profile: Profile, num_images: int) -> dict:
    """A Switch-NeRF method's memory model with the hash-grid networks (model/methods/ngp.py) in
    its main phase."""
    g = profile.ngp
    switch = sizes.switch_nerf(profile, num_images) + sizes.background(profile, num_images)
    hashed = sizes.ngp_field(profile, num_images) + sizes.ngp_background(profile, num_images)
    main = phases["main"]
    return {
        **phases,
        "main": replace(
            main,
            trained=main.trained - switch + hashed,
            bytes_per_sample=hash_grid_bytes_per_sample(g.levels, g.features, g.width),
            background_bytes_per_sample=(
                main.background_bytes_per_sample  # the Switch-NeRF methods' MLP
                if g.background == "mlp"
                else hash_grid_bytes_per_sample(g.background_levels, g.features, g.width)
            ),
        ),
    }


def ngp(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    return on_hash_grids(grid(profile, num_images, profile.ngp.grid), profile, num_images)


def ngp_leco(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    return on_hash_grids(leco(profile, num_images), profile, num_images)


def ngp_prop(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    return on_hash_grids(prop(profile, num_images), profile, num_images)


def ngp_leco_prop(profile: Profile, num_images: int) -> dict[str, PhaseMemory]:
    return on_hash_grids(leco_prop(profile, num_images), profile, num_images)
