"""Named size profiles (`paper`, `cpu`, `smoke`): the one pydantic schema for model sizes and
sampling that later stages (training config, API, benchmark) embed rather than copy. See
docs/PROFILES.md for each choice."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

MAX_STEPS = 10_000_000  # per phase; `leco bench --budget-min` uses this as "until the clock stops"
# Far past any rate that trains (Adam's steps are ~lr), low enough to stay finite in every product
# of the loop; the fault tests use it to blow a run up on purpose.
LR_MAX = 1e6


class Frozen(BaseModel):
    # Every number bounded on both sides and finite: a job that asks for more than any machine has
    # is refused at the API, not OOM-killed on a worker.
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class NetworkConfig(Frozen):
    width: int = Field(256, ge=8, le=2048)
    num_experts: int = Field(8, ge=1, le=64)
    expert_layers: int = Field(7, ge=1, le=16)
    xyz_frequencies: int = Field(12, ge=0, le=24)
    dir_frequencies: int = Field(4, ge=0, le=12)
    appearance_dim: int = Field(48, ge=1, le=512)
    capacity_factor: float | None = Field(None, gt=0, le=64)
    # N(0, s) on raw density while training (Switch-NeRF)
    density_noise: float = Field(1.0, ge=0, le=100)


class BackgroundConfig(Frozen):
    width: int = Field(128, ge=8, le=2048)
    layers: int = Field(4, ge=1, le=16)
    samples: int = Field(64, ge=1, le=1024)


class OccupancyPhaseConfig(Frozen):
    """Phase 1 of LeCO: the HMoE and its losses (paper section 4.3)."""

    samples_per_ray: int = Field(512, ge=2, le=4096)
    steps: int = Field(40_000, ge=1, le=MAX_STEPS)
    lr: float = Field(5e-4, gt=0, le=LR_MAX)
    lr_final: float | None = Field(None, gt=0, le=LR_MAX)  # decay to this by the phase's end;
    # None: constant (the paper)
    w_r: float = Field(1.0, ge=0, le=1e4)
    w_g: float = Field(5e-4, ge=0, le=1e4)
    # w_g decays log-linearly to this by the phase's end;
    w_g_final: float | None = Field(None, ge=0, le=1e4)
    # None: constant
    w_d: float = Field(0.1, ge=0, le=1e4)
    v: float = Field(80.0, gt=0, le=1e6)
    homogeneous: bool = False
    # E_e's size (the paper's Table 9): 0 is an identity layer (the paper's choice), N an N-layer
    # MLP; homogeneous makes it a scene expert's size instead.
    empty_expert_layers: int = Field(0, ge=0, le=16)
    # Not in the paper (docs/BENCHMARKS.md "ablation ladder"); 0 / True keep the paper's
    # formulation. visibility loss: visible samples (detached render weights) away from E_e
    w_v: float = Field(0.0, ge=0, le=1e4)
    # False: the rendering loss cannot raise E_e's gate (its value is detached)
    empty_gate_grad: bool = True
    # O's layers after the shared input layer; None: network.width
    gate_width: int | None = Field(None, ge=8, le=2048)
    # O's path: a ReLU after every hidden layer, not only between its inner two
    gate_relu_every_layer: bool = False
    # Under a wall-clock budget phase 1 stops at this share of it (or at `steps`, whichever comes
    # first); the main phase gets the rest
    budget_share: float = Field(0.25, gt=0, lt=1)


class GuidedConfig(Frozen):
    coarse_samples: int = Field(128, ge=1, le=4096)
    split: int = Field(8, ge=1, le=64)
    # Not in the paper; the defaults keep the paper's sampler and its from-scratch main network.
    # while training, query O at a random point of each coarse bin, not its mid-point
    jitter: bool = False
    # also keep bins up to this many bins before / after a kept bin
    dilate: int = Field(0, ge=0, le=64)
    fallback: bool = False  # a ray with no kept bin samples every coarse bin once instead of none
    # the main network starts from phase 1's experts, heads, background, embeddings
    warm_start: bool = False
    # After a warm start the main phase's lr rises linearly over this many steps (0: none). Adam's
    # first steps move every weight by about lr whatever its gradient, which may undo what the warm
    # start brought.
    warm_start_ramp: int = Field(0, ge=0, le=10**6)
    # keep p(E_e) < this; None: O's top-1 (the paper)
    empty_threshold: float | None = Field(None, gt=0, le=1)
    # nerfacc's early stop: a gradient-free pass drops samples the main field hides (T_i below
    # this); None: off
    cull_transmittance: float | None = Field(None, gt=0, lt=1)
    # O keeps learning in the main phase from the main network's detached weights
    # (model/online_occupancy.py)
    online: bool = False
    # ... a kept bin with this share of its ray's weight is a surface
    online_surface: float = Field(0.05, gt=0, lt=1)
    # ... O starts learning after this many main-phase steps
    online_warmup: int = Field(500, ge=0, le=10**7)
    # ... and then learns on every k-th step (its backward is not free)
    online_every: int = Field(1, ge=1, le=1000)
    # ... a kept bin is labelled free only on rays whose foreground opacity reaches this: where the
    # foreground is semi-transparent the background is painting what it misses, and "free" would
    # teach O to drop it (0: off)
    online_free_opacity: float = Field(0.0, ge=0, le=1)
    # O is asked at this many points of each coarse bin (stratified, jittered with `jitter`); a bin
    # is kept when any is. 1: one point per bin (the paper's mid-point)
    queries_per_bin: int = Field(1, ge=1, le=16)
    # The main phase's background starts from phase 1's (with warm_start). Phase 1's background
    # learned to paint what the HMoE's foreground missed (the ground of an aerial scene); False
    # starts it fresh.
    warm_start_background: bool = True
    # ... and the main head's density layer starts from phase 1's (False: fresh, the colours still
    # copied)
    warm_start_density: bool = True
    # With `fallback`, a ray with nothing kept gets O's k most likely bins (by its decision logit)
    # instead of one sample in every coarse bin (0)
    fallback_topk: int = Field(0, ge=0, le=4096)
    # O places the samples (model/placement.py): a one-unit density head on O, trained by the
    # interlevel loss against the main network's detached weights, and exactly `main_samples` per
    # hit ray drawn by inverse CDF over the kept (dilated) bins, in place of `split` stratified
    # samples per kept bin
    placement: bool = False
    main_samples: int = Field(21, ge=1, le=4096)
    placement_loss_weight: float = Field(1.0, ge=0, le=1e4)
    # added to every kept bin's weight (nerfstudio's padding)
    placement_padding: float = Field(0.01, ge=0, le=1)
    # uniform -> O's weights (nerfstudio's anneal)
    placement_anneal_steps: int = Field(500, ge=0, le=MAX_STEPS)
    # A kept bin whose share of O's (annealed) histogram on its ray is below this gets no sample: O
    # expects almost none of the ray's weight there (0: every kept bin may get one, by its padded
    # share)
    placement_min_share: float = Field(0.0, ge=0, lt=1)
    # ... and the head already learns in phase 1, against the HMoE's own detached weights, so the
    # main phase starts with a histogram that knows the scene
    placement_in_phase1: bool = False
    # ... in two passes (model/fine_placement.py): the coarse histogram places this many
    # intermediate intervals, O's head is asked at their mid-points, and the main samples follow
    # that finer histogram (0: one pass, the main samples spread evenly inside each kept bin's
    # share)
    placement_fine: int = Field(0, ge=0, le=1024)
    # O's placement losses (both passes) on every k-th main-phase step; on the others O places the
    # samples without gradient, as S+Prop's proposals do between updates (with `online_every` = k,
    # O's whole learning)
    placement_every: int = Field(1, ge=1, le=1000)
    # This share of each hit ray's main samples goes to the bins O dropped, by length
    # (model/placement.py `explored`), so the main network can show O a surface it dropped (0:
    # samples only in kept bins)
    placement_explore: float = Field(0.0, ge=0, lt=1)
    # How a kept bin's share of the samples spreads inside it (model/placement.py
    # `within_bin_shares`): evenly (uniform), by a density linear across the bin from its
    # neighbours' (linear), or as O's constant density in the bin puts its weight by volume
    # rendering, towards the front of an opaque bin (volume)
    placement_within: Literal["uniform", "linear", "volume"] = "uniform"

    @model_validator(mode="after")
    def options_need_their_switch(self) -> "GuidedConfig":
        # A setting that would be silently ignored is refused, naming the switch it needs.
        if self.fallback_topk > 0 and not self.fallback:
            raise ValueError(
                "guided.fallback_topk needs guided.fallback=true (it picks the fallback's bins); "
                "with guided.fallback=false set guided.fallback_topk=0 too"
            )
        if self.placement_in_phase1 and not self.placement:
            raise ValueError(
                "guided.placement_in_phase1 needs guided.placement=true (it trains O's placement "
                "head); with guided.placement=false set guided.placement_in_phase1=false too"
            )
        if self.placement_fine and not self.placement:
            raise ValueError(
                "guided.placement_fine needs guided.placement=true (it refines O's placement); "
                "with guided.placement=false set guided.placement_fine=0 too"
            )
        if self.placement_every > 1 and not self.placement:
            raise ValueError(
                "guided.placement_every needs guided.placement=true (it spaces O's placement "
                "updates); with guided.placement=false set guided.placement_every=1 too"
            )
        if self.placement_within != "uniform" and (not self.placement or self.placement_fine):
            raise ValueError(
                "guided.placement_within needs guided.placement=true and guided.placement_fine=0 "
                "(it shapes the one-pass draw); otherwise leave guided.placement_within=uniform"
            )
        if self.placement_explore > 0 and not self.placement:
            raise ValueError(
                "guided.placement_explore needs guided.placement=true (it shares O's placement "
                "budget); with guided.placement=false set guided.placement_explore=0 too"
            )
        if self.placement_fine and self.cull_transmittance is not None:
            raise ValueError(
                "guided.placement_fine and guided.cull_transmittance cannot be combined: the fine "
                "pass's loss needs every placed sample's weight; unset one of them"
            )
        return self

    def online_learns(self, main_step: int) -> bool:
        """Whether O learns at this main-phase step (0-based), given `online`, its warm-up and its
        period."""
        past_warmup = main_step - self.online_warmup
        return self.online and past_warmup >= 0 and past_warmup % self.online_every == 0

    def placement_learns(self, main_step: int) -> bool:
        """Whether O's placement losses run at this main-phase step (0-based), given
        `placement_every`."""
        return self.placement and main_step % self.placement_every == 0


class VanillaConfig(Frozen):
    coarse_samples: int = Field(256, ge=2, le=4096)
    fine_samples: int = Field(512, ge=0, le=8192)


class GridConfig(Frozen):
    resolution: int = Field(128, ge=4, le=512)
    update_every: int = Field(16, ge=1, le=MAX_STEPS)
    decay: float = Field(0.95, gt=0, lt=1)
    threshold: float = Field(0.01, gt=0, le=1e6)
    warmup_steps: int = Field(256, ge=0, le=MAX_STEPS)
    # samples across the box diagonal: sets the marching step size
    march_steps: int = Field(1024, ge=8, le=16384)


class ProposalConfig(Frozen):
    """S+Prop (model/methods/prop.py): proposal networks in place of Switch-NeRF's coarse/fine
    sampling."""

    # per proposal level (nerfacto's)
    samples: tuple[int, ...] = Field((256, 96), min_length=1, max_length=4)
    # Main-network samples per ray, set to LeCO's at the same profile (docs/PROFILES.md says how).
    main_samples: int = Field(148, ge=1, le=4096)
    # None: sized so all levels total LeCO's O (model/methods/prop.py)
    width: int | None = Field(None, ge=4, le=2048)
    layers: int = Field(2, ge=1, le=8)
    anneal_slope: float = Field(10.0, gt=0, le=1e3)  # nerfstudio's proposal_weights_anneal_slope
    # ... and proposal_weights_anneal_max_num_iters
    anneal_steps: int = Field(1000, ge=0, le=MAX_STEPS)
    # nerfacc's get_proposal_requires_grad_fn(target=5, num_steps=1000)
    update_every: int = Field(5, ge=1, le=1000)
    update_warmup: int = Field(1000, ge=0, le=MAX_STEPS)
    histogram_padding: float = Field(0.01, ge=0, le=1)  # nerfstudio's PDFSampler default
    loss_weight: float = Field(1.0, ge=0, le=1e4)  # nerfstudio's interlevel_loss_mult

    @field_validator("samples")
    @classmethod
    def positive(cls, samples: tuple[int, ...]) -> tuple[int, ...]:
        if any(not 2 <= n <= 4096 for n in samples):
            raise ValueError("every proposal level needs 2 to 4096 samples")
        return samples


class Profile(Frozen):
    name: str
    network: NetworkConfig = NetworkConfig()
    background: BackgroundConfig = BackgroundConfig()
    occupancy: OccupancyPhaseConfig = OccupancyPhaseConfig()
    guided: GuidedConfig = GuidedConfig()
    vanilla: VanillaConfig = VanillaConfig()
    grid: GridConfig = GridConfig()
    prop: ProposalConfig = ProposalConfig()
    rays_per_device: int = Field(1024, ge=1, le=65536)
    # Switch-NeRF (guided or not) steps after any occupancy phase
    main_steps: int = Field(500_000, ge=1, le=MAX_STEPS)
    balance_weight: float = Field(5e-4, ge=0, le=1e4)  # Switch-NeRF's balance loss
    # jittered samples while training; off makes a step deterministic given the rays
    perturb: bool = True
    lr: float = Field(5e-4, gt=0, le=LR_MAX)
    lr_final: float = Field(5e-5, gt=0, le=LR_MAX)


PROFILES: dict[str, Profile] = {
    "paper": Profile(name="paper"),
    "cpu": Profile(
        name="cpu",
        network=NetworkConfig(width=64, num_experts=8, expert_layers=4),
        background=BackgroundConfig(width=32, layers=2, samples=16),
        # Measured settings beyond the paper (docs/BENCHMARKS.md, ablation ladder);
        # bench/variants.py PAPER_FORMULATION undoes them.
        occupancy=OccupancyPhaseConfig(
            samples_per_ray=64,
            steps=1500,
            lr=2e-3,
            w_g=5e-2,
            empty_gate_grad=False,
            budget_share=0.15,
        ),
        guided=GuidedConfig(
            coarse_samples=16,
            split=4,
            dilate=1,
            jitter=True,
            fallback=True,
            warm_start=True,
            empty_threshold=0.9,
            online=True,
            warm_start_background=False,
            online_free_opacity=0.5,
            fallback_topk=2,
            placement=True,
            placement_in_phase1=True,
            main_samples=21,
            placement_padding=0.001,
        ),
        vanilla=VanillaConfig(coarse_samples=32, fine_samples=64),
        grid=GridConfig(resolution=128, march_steps=256),
        # LeCO's main samples per ray on the city at this profile: 21.2 (8-minute benchmark,
        # docs/BENCHMARKS.md).
        prop=ProposalConfig(samples=(64, 32), main_samples=21),
        rays_per_device=256,
        main_steps=1500,
        lr=2e-3,
        lr_final=2e-4,
    ),
    "smoke": Profile(
        name="smoke",
        network=NetworkConfig(
            width=16,
            num_experts=2,
            expert_layers=2,
            xyz_frequencies=6,
            dir_frequencies=2,
            appearance_dim=8,
        ),
        background=BackgroundConfig(width=8, layers=1, samples=4),
        occupancy=OccupancyPhaseConfig(samples_per_ray=16, steps=20, lr=5e-3, w_g=5e-2),
        guided=GuidedConfig(coarse_samples=8, split=4),
        vanilla=VanillaConfig(coarse_samples=8, fine_samples=16),
        grid=GridConfig(resolution=32, warmup_steps=4, update_every=4, march_steps=64),
        prop=ProposalConfig(samples=(16, 8), main_samples=8, anneal_steps=10, update_warmup=10),
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
