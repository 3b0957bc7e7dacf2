"""Named size profiles (`paper`, `cpu`, `smoke`): the one pydantic schema for model sizes and sampling that
later stages (training config, API, benchmark) embed rather than copy. See docs/PROFILES.md for each choice."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class NetworkConfig(Frozen):
    width: int = Field(256, ge=8)
    num_experts: int = Field(8, ge=1)
    expert_layers: int = Field(7, ge=1)
    xyz_frequencies: int = Field(12, ge=0)
    dir_frequencies: int = Field(4, ge=0)
    appearance_dim: int = Field(48, ge=1)
    capacity_factor: float | None = Field(None, gt=0)
    density_noise: float = Field(1.0, ge=0)  # N(0, s) on raw density while training (Switch-NeRF)


class BackgroundConfig(Frozen):
    width: int = Field(128, ge=8)
    layers: int = Field(4, ge=1)
    samples: int = Field(64, ge=1)


class OccupancyPhaseConfig(Frozen):
    """Phase 1 of LeCO: the HMoE and its losses (paper section 4.3)."""

    samples_per_ray: int = Field(512, ge=2)
    steps: int = Field(40_000, ge=1)
    lr: float = Field(5e-4, gt=0)
    lr_final: float | None = Field(None, gt=0)  # decay to this by the phase's end; None: constant (the paper)
    w_r: float = Field(1.0, ge=0)
    w_g: float = Field(5e-4, ge=0)
    w_g_final: float | None = Field(None, ge=0)  # w_g decays log-linearly to this by the phase's end; None: constant
    w_d: float = Field(0.1, ge=0)
    v: float = Field(80.0, gt=0)
    homogeneous: bool = False
    # Not in the paper (issue 16, docs/BENCHMARKS.md "ablation ladder"); 0 / True keep the paper's formulation.
    w_v: float = Field(0.0, ge=0)  # visibility loss: visible samples (detached render weights) away from E_e
    empty_gate_grad: bool = True  # False: the rendering loss cannot raise E_e's gate (its value is detached)


class GuidedConfig(Frozen):
    coarse_samples: int = Field(128, ge=1)
    split: int = Field(8, ge=1)
    # Not in the paper (issue 16); the defaults keep the paper's sampler and its from-scratch main network.
    jitter: bool = False  # while training, query O at a random point of each coarse bin, not its mid-point
    dilate: int = Field(0, ge=0)  # also keep bins up to this many bins before / after a kept bin
    fallback: bool = False  # a ray with no kept bin samples every coarse bin once instead of none
    warm_start: bool = False  # the main network starts from phase 1's experts, heads, background, embeddings
    empty_threshold: float | None = Field(None, gt=0, le=1)  # keep p(E_e) < this; None: O's top-1 (the paper)


class VanillaConfig(Frozen):
    coarse_samples: int = Field(256, ge=2)
    fine_samples: int = Field(512, ge=0)


class GridConfig(Frozen):
    resolution: int = Field(128, ge=4)
    update_every: int = Field(16, ge=1)
    decay: float = Field(0.95, gt=0, lt=1)
    threshold: float = Field(0.01, gt=0)
    warmup_steps: int = Field(256, ge=0)
    march_steps: int = Field(1024, ge=8)  # samples across the box diagonal: sets the marching step size


class Profile(Frozen):
    name: str
    network: NetworkConfig = NetworkConfig()
    background: BackgroundConfig = BackgroundConfig()
    occupancy: OccupancyPhaseConfig = OccupancyPhaseConfig()
    guided: GuidedConfig = GuidedConfig()
    vanilla: VanillaConfig = VanillaConfig()
    grid: GridConfig = GridConfig()
    rays_per_device: int = Field(1024, ge=1)
    main_steps: int = Field(500_000, ge=1)  # Switch-NeRF (guided or not) steps after any occupancy phase
    balance_weight: float = Field(5e-4, ge=0)  # Switch-NeRF's balance loss
    perturb: bool = True  # jittered samples while training; off makes a step deterministic given the rays
    lr: float = Field(5e-4, gt=0)
    lr_final: float = Field(5e-5, gt=0)


PROFILES: dict[str, Profile] = {
    "paper": Profile(name="paper"),
    "cpu": Profile(
        name="cpu",
        network=NetworkConfig(width=64, num_experts=8, expert_layers=4),
        background=BackgroundConfig(width=32, layers=2, samples=16),
        # Issue 16's measured settings (docs/BENCHMARKS.md, ablation ladder); bench/variants.py PAPER_FORMULATION
        # undoes them.
        occupancy=OccupancyPhaseConfig(samples_per_ray=64, steps=1500, lr=2e-3, w_g=5e-2, empty_gate_grad=False),
        guided=GuidedConfig(coarse_samples=16, split=4, dilate=2, jitter=True, fallback=True, warm_start=True,
                            empty_threshold=0.9),
        vanilla=VanillaConfig(coarse_samples=32, fine_samples=64),
        grid=GridConfig(resolution=128, march_steps=256),
        rays_per_device=256,
        main_steps=1500,
        lr=2e-3,
        lr_final=2e-4,
    ),
    "smoke": Profile(
        name="smoke",
        network=NetworkConfig(width=16, num_experts=2, expert_layers=2, xyz_frequencies=6, dir_frequencies=2,
                              appearance_dim=8),
        background=BackgroundConfig(width=8, layers=1, samples=4),
        occupancy=OccupancyPhaseConfig(samples_per_ray=16, steps=20, lr=5e-3, w_g=5e-2),
        guided=GuidedConfig(coarse_samples=8, split=4),
        vanilla=VanillaConfig(coarse_samples=8, fine_samples=16),
        grid=GridConfig(resolution=32, warmup_steps=4, update_every=4, march_steps=64),
        rays_per_device=64,
        main_steps=20,
        lr=5e-3,
        lr_final=5e-4,
    ),
}


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}: choose one of {', '.join(PROFILES)}")
    return PROFILES[name]
