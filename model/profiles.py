"""Named size profiles (`paper`, `cpu`, `smoke`): the one pydantic schema for model sizes and
sampling that later stages (training config, API, benchmark) embed rather than copy. See
docs/PROFILES.md for each choice."""

from __future__ import annotations

from typing import Any, Literal

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
    """The main network: Switch-NeRF's mixture of scene experts behind a gate."""

    width: int = Field(256, ge=8, le=2048, description="hidden units per expert layer")
    num_experts: int = Field(8, ge=1, le=64, description="scene experts the gate chooses among")
    expert_layers: int = Field(7, ge=1, le=16, description="hidden layers per scene expert")
    xyz_frequencies: int = Field(
        12, ge=0, le=24, description="positional-encoding frequencies of a point"
    )
    dir_frequencies: int = Field(
        4, ge=0, le=12, description="positional-encoding frequencies of a view direction"
    )
    appearance_dim: int = Field(
        48, ge=1, le=512, description="length of each image's appearance embedding"
    )
    capacity_factor: float | None = Field(
        None,
        gt=0,
        le=64,
        description="Switch-NeRF's expert capacity (points per expert, as a multiple of an even "
        "share); None: no cap",
    )
    density_noise: float = Field(
        1.0, ge=0, le=100, description="N(0, s) added to raw density while training (Switch-NeRF)"
    )


class BackgroundConfig(Frozen):
    """The background model: what lies outside the foreground box (Mega-NeRF's)."""

    width: int = Field(128, ge=8, le=2048, description="hidden units per layer")
    layers: int = Field(4, ge=1, le=16, description="hidden layers")
    samples: int = Field(64, ge=1, le=1024, description="samples per ray beyond the box")
    sky_at_infinity: bool = Field(
        False,
        description="the opaque last background sample is taken at infinity, so the sky is a "
        "function of the direction alone, the same for every view (off: at 2 x samples x the "
        "box's exit distance, where each camera sees it through other points)",
    )


class OccupancyPhaseConfig(Frozen):
    """Phase 1 of LeCO: the HMoE and its losses (paper section 4.3). The settings after
    `homogeneous` are not in the paper (docs/EXPERIMENTS.md, the ablation ladder); their defaults
    keep the paper's formulation."""

    samples_per_ray: int = Field(512, ge=2, le=4096, description="HMoE samples per ray")
    steps: int = Field(
        40_000, ge=1, le=MAX_STEPS, description="phase-1 steps (a budget may stop it sooner)"
    )
    lr: float = Field(5e-4, gt=0, le=LR_MAX, description="Adam learning rate")
    lr_final: float | None = Field(
        None,
        gt=0,
        le=LR_MAX,
        description="the lr decays to this by the phase's end; None: constant (the paper)",
    )
    w_r: float = Field(
        1.0, ge=0, le=1e4, description="w_r: weight of the rendering loss L_r in the final loss L_f"
    )
    w_g: float = Field(
        5e-4, ge=0, le=1e4, description="w_g: weight of the imbalanced gate loss L_g (Eq. 1) in L_f"
    )
    w_g_final: float | None = Field(
        None,
        ge=0,
        le=1e4,
        description="w_g decays log-linearly to this by the phase's end; None: constant",
    )
    w_d: float = Field(
        0.1, ge=0, le=1e4, description="w_d: weight of the density loss L_d (Eq. 2) in L_f"
    )
    v: float = Field(80.0, gt=0, le=1e6, description="L_g counts E_e as v virtual experts (Eq. 1)")
    homogeneous: bool = Field(
        False, description="the empty expert is a scene expert's size (the paper's Table 9)"
    )
    empty_expert_layers: int = Field(
        0,
        ge=0,
        le=16,
        description="E_e's size (the paper's Table 9): 0 is an identity layer (the paper's "
        "choice), N an N-layer MLP",
    )
    w_v: float = Field(
        0.0,
        ge=0,
        le=1e4,
        description="visibility loss: visible samples (detached render weights) pushed away from "
        "E_e; 0: off",
    )
    empty_gate_grad: bool = Field(
        True,
        description="False: the rendering loss cannot raise E_e's gate (its value is detached)",
    )
    gate_width: int | None = Field(
        None,
        ge=8,
        le=2048,
        description="O's layers after the shared input layer; None: network.width",
    )
    gate_relu_every_layer: bool = Field(
        False, description="O: a ReLU after every hidden layer, not only between its inner two"
    )
    budget_share: float = Field(
        0.25,
        gt=0,
        lt=1,
        description="under a wall-clock budget phase 1 stops at this share of it (or at `steps`); "
        "the main phase gets the rest",
    )
    min_steps: int = Field(
        0,
        ge=0,
        le=MAX_STEPS,
        description="under a wall-clock budget phase 1 takes at least this many steps (at most "
        "`steps`) before it stops at its share, while the budget lasts: a short budget's share "
        "may be too few steps for O to become selective",
    )


class GuidedConfig(Frozen):
    """The main phase of LeCO: how O guides Switch-NeRF's samples. Only `coarse_samples` and `split`
    are the paper's; the defaults of the rest keep the paper's sampler and its from-scratch main
    network (docs/EXPERIMENTS.md measures each)."""

    coarse_samples: int = Field(
        128, ge=1, le=4096, description="coarse bins per ray, each one query of O"
    )
    split: int = Field(
        8, ge=1, le=64, description="stratified main samples per kept bin (without placement)"
    )
    jitter: bool = Field(
        False,
        description="while training, query O at a random point of each coarse bin, not its "
        "mid-point",
    )
    dilate: int = Field(
        0, ge=0, le=64, description="also keep bins up to this many bins before / after a kept bin"
    )
    fallback: bool = Field(
        False, description="a ray with no kept bin samples every coarse bin once instead of none"
    )
    warm_start: bool = Field(
        False,
        description="the main network starts from phase 1's experts, heads, background and "
        "embeddings",
    )
    warm_start_ramp: int = Field(
        0,
        ge=0,
        le=10**6,
        description="after a warm start the main phase's lr rises linearly over this many steps "
        "(0: none); Adam's first steps move every weight by about lr",
    )
    empty_threshold: float | None = Field(
        None, gt=0, le=1, description="keep a bin where p(E_e) < this; None: O's top-1 (the paper)"
    )
    cull_transmittance: float | None = Field(
        None,
        gt=0,
        lt=1,
        description="nerfacc's early stop: a gradient-free pass drops samples the main field hides "
        "(T_i below this); None: off",
    )
    online: bool = Field(
        False,
        description="O keeps learning in the main phase from the main network's detached weights "
        "(model/estimators/online.py)",
    )
    online_surface: float = Field(
        0.05,
        gt=0,
        lt=1,
        description="online: a kept bin with this share of its ray's weight is a surface",
    )
    online_warmup: int = Field(
        500, ge=0, le=10**7, description="online: O starts learning after this many main steps"
    )
    online_every: int = Field(
        1,
        ge=1,
        le=1000,
        description="online: O learns on every k-th step (its backward is not free)",
    )
    online_free_opacity: float = Field(
        0.0,
        ge=0,
        le=1,
        description="online: a kept bin is labelled free only on rays whose foreground opacity "
        "reaches this, so O is not taught to drop what the background paints (0: off)",
    )
    online_free_error: float = Field(
        0.0,
        ge=0,
        le=1,
        description="online: a kept bin is labelled free only on rays whose squared colour error "
        "(mean over RGB) is at most this: a ray the field still renders wrong may pass a surface "
        "it has not fitted yet (a roof's top it grazes), so it does not teach O to drop it "
        "(0: off)",
    )
    online_surface_points: bool = Field(
        False,
        description="online: O is also taught to keep each opaque ray's most visible main sample, "
        "at its own point (a bin's label reaches O at one random point of the bin, where a thin "
        "surface may not be)",
    )
    online_dense_points: bool = Field(
        False,
        description="online: O is also taught to keep every main sample that stops at least "
        "`online_surface` of the light reaching it while half the ray's light still gets there "
        "(a top a ray grazes on its way to the ground is not the point the ray shows most, so "
        "`online_surface_points` does not teach it)",
    )
    online_box_points: int = Field(
        0,
        ge=0,
        le=1 << 20,
        description="online: O is also taught at this many points drawn uniformly over the scene's "
        "box on each step it learns, kept where the main field's alpha over one step of the box "
        "diagonal / 256 reaches `online_box_alpha` and dropped elsewhere: labels for the whole "
        "box from the field's density, as Instant-NGP's grid is updated (the points are charged "
        "to the step's samples; 0: off)",
    )
    online_box_alpha: float = Field(
        0.01,
        gt=0,
        lt=1,
        description="online_box_points: a point is occupied where the main field stops this share "
        "of the light over one step (nerfacc's grid threshold)",
    )
    queries_per_bin: int = Field(
        1,
        ge=1,
        le=16,
        description="O is asked at this many points of each coarse bin and a bin is kept when any "
        "is (1: the paper's mid-point)",
    )
    warm_start_background: bool = Field(
        True,
        description="with warm_start, the main phase's background starts from phase 1's, which "
        "learned to paint what the HMoE missed; False: fresh",
    )
    warm_start_density: bool = Field(
        True,
        description="with warm_start, the main head's density layer starts from phase 1's "
        "(False: fresh; the colours are still copied)",
    )
    fallback_topk: int = Field(
        0,
        ge=0,
        le=4096,
        description="with fallback, a ray with nothing kept gets O's k most likely bins instead of "
        "one sample in every coarse bin (0)",
    )
    placement: bool = Field(
        False,
        description="O places the samples (model/estimators/placement.py): a density head on O "
        "trained by the interlevel loss, `main_samples` per hit ray by inverse CDF over the kept "
        "bins",
    )
    main_samples: int = Field(21, ge=1, le=4096, description="placement: main samples per hit ray")
    placement_loss_weight: float = Field(
        1.0, ge=0, le=1e4, description="placement: weight of the interlevel loss on O"
    )
    placement_padding: float = Field(
        0.01,
        ge=0,
        le=1,
        description="placement: added to every kept bin's weight (nerfstudio's histogram padding)",
    )
    placement_anneal_steps: int = Field(
        500,
        ge=0,
        le=MAX_STEPS,
        description="placement: steps from uniform to O's weights (nerfstudio's anneal)",
    )
    placement_min_share: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="placement: a kept bin with less than this share of O's histogram on its ray "
        "gets no sample (0: every kept bin may get one)",
    )
    placement_in_phase1: bool = Field(
        False,
        description="placement: the head already learns in phase 1, against the HMoE's detached "
        "weights",
    )
    placement_fine: int = Field(
        0,
        ge=0,
        le=1024,
        description="placement in two passes (model/estimators/fine_placement.py): this many "
        "intermediate intervals asked of O again (0: one pass)",
    )
    placement_every: int = Field(
        1,
        ge=1,
        le=1000,
        description="placement: O's placement losses on every k-th main step; on the others it "
        "places without gradient, as S+Prop's proposals do",
    )
    placement_explore: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="placement: this share of each hit ray's samples goes to the bins O dropped, "
        "by length (0: samples only in kept bins)",
    )
    placement_within: Literal["uniform", "linear", "volume"] = Field(
        "uniform",
        description="placement: how a kept bin's samples spread inside it: evenly, by a density "
        "linear from its neighbours', or by volume rendering of O's density in the bin",
    )
    explore_bins: int = Field(
        0,
        ge=0,
        le=64,
        description="while training, each hit ray also samples this many of the bins O dropped, "
        "drawn at random every step and split like kept bins, so a surface O missed is rendered "
        "and, while O learns online, taught to it (0: only the bins O keeps; with placement, "
        "placement_explore does this)",
    )

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
        if self.explore_bins and self.placement:
            raise ValueError(
                "guided.explore_bins samples dropped bins by splitting them, which placement does "
                "not do: with guided.placement=true use guided.placement_explore instead"
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
    """Switch-NeRF's own sampler: Mega-NeRF's coarse/fine hierarchical sampling."""

    coarse_samples: int = Field(256, ge=2, le=4096, description="coarse samples per ray")
    fine_samples: int = Field(
        512, ge=0, le=8192, description="fine samples per ray, by the coarse weights"
    )


class GridConfig(Frozen):
    """S+Grid: an Instant-NGP-style occupancy grid (nerfacc's OccGridEstimator)."""

    resolution: int = Field(128, ge=4, le=512, description="cells per side of the grid")
    update_every: int = Field(
        16, ge=1, le=MAX_STEPS, description="steps between updates of the grid's densities"
    )
    decay: float = Field(0.95, gt=0, lt=1, description="EMA decay of a cell's density per update")
    threshold: float = Field(
        0.01, gt=0, le=1e6, description="a cell whose density reaches this is occupied"
    )
    warmup_steps: int = Field(
        256, ge=0, le=MAX_STEPS, description="steps during which every cell is updated"
    )
    march_steps: int = Field(
        1024,
        ge=8,
        le=16384,
        description="samples across the box diagonal: sets the marching step size",
    )
    levels: int = Field(
        1,
        ge=1,
        le=8,
        description="cascades: level l covers the box scaled by 2^l about its centre at the same "
        "resolution and culls the background's samples there (Instant-NGP's; 1: the box only)",
    )
    early_stop_eps: float = Field(
        1e-4,
        ge=0,
        lt=1,
        description="image renders (validation, renders, exports) stop a ray once its "
        "transmittance falls below this (Instant-NGP's and nerfacc's 1e-4; 0: every sample); "
        "training keeps every sample",
    )


class ProposalConfig(Frozen):
    """S+Prop (model/methods/prop.py): proposal networks in place of Switch-NeRF's coarse/fine
    sampling."""

    samples: tuple[int, ...] = Field(
        (256, 96),
        min_length=1,
        max_length=4,
        description="samples per proposal level (nerfacto's)",
    )
    main_samples: int = Field(
        148,
        ge=1,
        le=4096,
        description="main-network samples per ray, set to LeCO's at the same profile "
        "(docs/PROFILES.md)",
    )
    width: int | None = Field(
        None,
        ge=4,
        le=2048,
        description="hidden units; None: sized so all levels total LeCO's O",
    )
    layers: int = Field(2, ge=1, le=8, description="hidden layers per proposal network")
    anneal_slope: float = Field(
        10.0, gt=0, le=1e3, description="nerfstudio's proposal_weights_anneal_slope"
    )
    anneal_steps: int = Field(
        1000,
        ge=0,
        le=MAX_STEPS,
        description="nerfstudio's proposal_weights_anneal_max_num_iters",
    )
    update_every: int = Field(
        5,
        ge=1,
        le=1000,
        description="the proposals learn on every k-th step after the warm-up (nerfacc's "
        "get_proposal_requires_grad_fn)",
    )
    update_warmup: int = Field(
        1000, ge=0, le=MAX_STEPS, description="steps during which the proposals learn every step"
    )
    histogram_padding: float = Field(
        0.01, ge=0, le=1, description="nerfstudio's PDFSampler histogram padding"
    )
    loss_weight: float = Field(
        1.0, ge=0, le=1e4, description="weight of the interlevel loss (interlevel_loss_mult)"
    )
    static_shapes: bool = Field(
        False,
        description="rays that miss the box ride along with an empty segment (zero weight) "
        "instead of being picked out: every tensor of a step has a fixed shape and the sampler "
        "reads nothing from the device (capture-safe, for CUDA graphs), at the cost of the "
        "misses' samples",
    )

    @field_validator("samples")
    @classmethod
    def positive(cls, samples: tuple[int, ...]) -> tuple[int, ...]:
        if any(not 2 <= n <= 4096 for n in samples):
            raise ValueError("every proposal level needs 2 to 4096 samples")
        return samples


class NGPConfig(Frozen):
    """The hash-grid field of `ngp`, `ngp-leco` and `ngp-prop` (model/fields/ngp.py): Instant-NGP's
    encoding and MLPs for the box, and a smaller hash grid on the contracted space for the
    background. The defaults are Instant-NGP's (Müller et al. 2022, Table 1 and section 5.4)."""

    levels: int = Field(16, ge=1, le=32, description="hash-encoding levels L")
    features: int = Field(2, ge=1, le=8, description="features per level F")
    log2_table_size: int = Field(
        19, ge=8, le=24, description="log2 of the entries T of each level's hash table"
    )
    min_resolution: int = Field(
        16, ge=2, le=1024, description="cells per side of the coarsest level N_min"
    )
    max_resolution: int = Field(
        2048, ge=2, le=65536, description="cells per side of the finest level N_max"
    )
    width: int = Field(64, ge=8, le=256, description="hidden units of the density and colour MLPs")
    background_levels: int = Field(
        16, ge=1, le=32, description="the background's hash-encoding levels"
    )
    background_log2_table_size: int = Field(
        19, ge=8, le=24, description="log2 of the background's table entries per level"
    )
    background_max_resolution: int = Field(
        2048, ge=2, le=65536, description="cells per side of the background's finest level"
    )
    background: Literal["hash", "mlp"] = Field(
        "hash",
        description="the far field: hash (a hash grid on the contracted space, Instant-NGP's and "
        "nerfacto's) or mlp (the Switch-NeRF methods' NeRF++ MLP on the inverted sphere, at the "
        "profile's lr and `background.*` sizes)",
    )
    distortion_weight: float = Field(
        0.0,
        ge=0,
        le=1,
        description="weight of mip-NeRF 360's distortion loss on the main samples' weights "
        "(nerfacto's: 0.002); 0: off",
    )
    grid: GridConfig = Field(
        GridConfig(levels=4),
        description="`ngp`'s own occupancy grid: Instant-NGP's 128^3 cells per cascade; 4 "
        "cascades (nerfacc's for unbounded scenes)",
    )
    lr: float = Field(
        1e-2, gt=0, le=LR_MAX, description="the main phase's Adam learning rate (Instant-NGP's)"
    )
    lr_final: float = Field(
        1e-3, gt=0, le=LR_MAX, description="the main phase's lr decays to this by its end"
    )
    # A hash entry sees few samples a step, so its gradients are weak: an eps of PyTorch's 1e-8
    # would shrink its Adam steps wherever |g| is below it (Instant-NGP trains with 1e-15)
    adam_eps: float = Field(
        1e-15, gt=0, le=1e-3, description="the main phase's Adam epsilon (Instant-NGP's)"
    )
    adam_beta2: float = Field(
        0.99, gt=0, lt=1, description="the main phase's Adam beta2 (Instant-NGP's)"
    )

    @model_validator(mode="after")
    def finest_not_below_coarsest(self) -> "NGPConfig":
        if self.max_resolution < self.min_resolution:
            raise ValueError(
                f"ngp.max_resolution ({self.max_resolution}) is below ngp.min_resolution "
                f"({self.min_resolution}): the finest level cannot be coarser than the first"
            )
        return self


class NGPLeCOConfig(Frozen):
    """NGP+LeCO's own phase 1 and sampler (`ngp-leco`): the hash field wants a sampler other than
    the MLP's (docs/EXPERIMENTS.md), so it reads these in place of `occupancy` and `guided`, which
    are `leco`'s. The paper profile keeps the paper's for both."""

    occupancy: OccupancyPhaseConfig = Field(
        OccupancyPhaseConfig(), description="ngp-leco's phase 1 (as `occupancy` is leco's)"
    )
    guided: GuidedConfig = Field(
        GuidedConfig(), description="ngp-leco's main-phase sampler (as `guided` is leco's)"
    )


class LeCOPropConfig(Frozen):
    """LeCO+Prop (`leco-prop`, `ngp-leco-prop`, model/methods/leco_prop.py): phase 1 as LeCO's,
    then proposal networks that sample only where O lets them. It reads these in place of
    `occupancy`, `guided` and `prop`, which are `leco`'s and `prop`'s."""

    bound: Literal["range", "mask", "level", "off"] = Field(
        "range",
        description="where O lets the proposals sample: range, each ray from its first kept bin "
        "to its last; mask, the kept bins only, end to end; level, as mask with O's placement "
        "histogram over them as the first proposal level (needs leco_prop.guided.placement); off, "
        "the whole segment (S+Prop after phase 1 and the warm start: the control)",
    )
    explore: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="a bin outside the bound keeps this share of its length on the proposals' "
        "axis, so a few samples look where O says nothing is and O can learn a surface it missed "
        "(0: none)",
    )
    prop_in_phase1: bool = Field(
        False,
        description="the proposals already learn in phase 1, from the HMoE's detached weights "
        "over the whole segment (the interlevel loss), so the main phase starts with proposals "
        "that know where the weight lies",
    )
    occupancy: OccupancyPhaseConfig = Field(
        OccupancyPhaseConfig(), description="leco-prop's phase 1 (as `occupancy` is leco's)"
    )
    guided: GuidedConfig = Field(
        GuidedConfig(),
        description="how O keeps bins in leco-prop's main phase (as `guided` is leco's; the "
        "placement settings are not read: the proposals place the samples)",
    )
    prop: ProposalConfig = Field(
        ProposalConfig(), description="leco-prop's proposal levels (as `prop` is S+Prop's)"
    )

    @model_validator(mode="after")
    def level_needs_placement(self) -> "LeCOPropConfig":
        if self.bound == "level" and not self.guided.placement:
            raise ValueError(
                "leco_prop.bound=level draws the first level from O's placement histogram: set "
                "leco_prop.guided.placement=true too"
            )
        if self.guided.explore_bins:
            raise ValueError(
                "leco_prop.guided.explore_bins is LeCO's split sampler's; LeCO+Prop's proposals "
                "look outside O's bound with leco_prop.explore"
            )
        if self.prop.static_shapes:
            raise ValueError(
                "leco_prop.prop.static_shapes: LeCO+Prop packs the bins O keeps, whose number only "
                "the device knows, so its step has no fixed shapes; prop.static_shapes is "
                "S+Prop's and NGP+Prop's"
            )
        return self


class Profile(Frozen):
    """Sizes and sampling of every method at one scale; a job may override any field."""

    name: str = Field(description="the profile's name (paper, cpu, smoke)")
    network: NetworkConfig = NetworkConfig()
    background: BackgroundConfig = BackgroundConfig()
    occupancy: OccupancyPhaseConfig = OccupancyPhaseConfig()
    guided: GuidedConfig = GuidedConfig()
    vanilla: VanillaConfig = VanillaConfig()
    grid: GridConfig = GridConfig()
    prop: ProposalConfig = ProposalConfig()
    ngp: NGPConfig = NGPConfig()
    ngp_leco: NGPLeCOConfig = NGPLeCOConfig()
    leco_prop: LeCOPropConfig = LeCOPropConfig()
    rays_per_device: int = Field(1024, ge=1, le=65536, description="rays per step per worker")
    main_steps: int = Field(
        500_000,
        ge=1,
        le=MAX_STEPS,
        description="Switch-NeRF steps (guided or not) after any occupancy phase",
    )
    balance_weight: float = Field(
        5e-4, ge=0, le=1e4, description="weight of Switch-NeRF's balance loss"
    )
    perturb: bool = Field(
        True,
        description="jittered samples while training; off makes a step deterministic given the "
        "rays",
    )
    lr: float = Field(5e-4, gt=0, le=LR_MAX, description="the main phase's Adam learning rate")
    lr_final: float = Field(
        5e-5, gt=0, le=LR_MAX, description="the main phase's lr decays to this by its end"
    )


def changed(section: Frozen, **values: object) -> Any:
    """A validated copy of a profile section with some values changed."""
    return type(section).model_validate({**section.model_dump(), **values})


# LeCO's phase 1 and sampler at `cpu`: measured settings beyond the paper (docs/EXPERIMENTS.md,
# the ablation ladder); bench/variants.py PAPER_FORMULATION undoes them.
CPU_OCCUPANCY = OccupancyPhaseConfig(
    samples_per_ray=64,
    steps=1500,
    lr=2e-3,
    w_g=5e-2,
    empty_gate_grad=False,
    budget_share=0.15,
)
CPU_GUIDED = GuidedConfig(
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
)
# LeCO's main samples per ray on the city at this profile: 21.2 (8-minute benchmark, 2026-11-24), so
# S+Prop's main network does the same work.
CPU_PROP = ProposalConfig(samples=(64, 32), main_samples=21)
SMOKE_OCCUPANCY = OccupancyPhaseConfig(samples_per_ray=16, steps=20, lr=5e-3, w_g=5e-2)
SMOKE_GUIDED = GuidedConfig(coarse_samples=8, split=4)
SMOKE_PROP = ProposalConfig(samples=(16, 8), main_samples=8, anneal_steps=10, update_warmup=10)


PROFILES: dict[str, Profile] = {
    "paper": Profile(name="paper"),
    "cpu": Profile(
        name="cpu",
        network=NetworkConfig(width=64, num_experts=8, expert_layers=4),
        background=BackgroundConfig(width=32, layers=2, samples=16),
        occupancy=CPU_OCCUPANCY,
        guided=CPU_GUIDED,
        vanilla=VanillaConfig(coarse_samples=32, fine_samples=64),
        grid=GridConfig(resolution=128, march_steps=256),
        prop=CPU_PROP,
        # Sized for this machine's minutes (docs/PROFILES.md): 8 levels up to 512 cells a side,
        # 2^16 entries each, and a 4-level background.
        ngp=NGPConfig(
            levels=8,
            log2_table_size=16,
            max_resolution=512,
            background_levels=4,
            background_log2_table_size=14,
            background_max_resolution=128,
            # 64^3 a cascade: the update then costs about a quarter of a step, as on a GPU,
            # where 128^3 at 2 cores costs three times the training (docs/PROFILES.md)
            grid=GridConfig(resolution=64, march_steps=256, levels=2),
        ),
        ngp_leco=NGPLeCOConfig(
            # O keeps or drops 64 bins a ray and the hash field gets 2 even samples in each kept bin
            # and its neighbours; O learns online from main step 250 and phase 1 takes 8% of the
            # budget (docs/EXPERIMENTS.md: where O's placement fell 1.7 dB short of NGP on lego)
            occupancy=changed(CPU_OCCUPANCY, budget_share=0.08),
            guided=changed(
                CPU_GUIDED,
                coarse_samples=64,
                split=2,
                dilate=1,
                placement=False,
                placement_in_phase1=False,
                online_warmup=250,
                # O is also taught the point each opaque ray shows: on the held-out suite +0.38 dB
                # over scenes, recall up on every synthetic scene (docs/EXPERIMENTS.md)
                online_surface_points=True,
                # twice the MLP LeCO's 21: the hash field resolves finer surfaces
                main_samples=42,
            ),
        ),
        leco_prop=LeCOPropConfig(
            occupancy=CPU_OCCUPANCY,
            # O keeps and drops bins as LeCO's does; the proposals, not O's head, place the samples
            guided=changed(CPU_GUIDED, placement=False, placement_in_phase1=False),
            # the first level over the kept length only: half S+Prop's 64 over the whole segment
            prop=changed(CPU_PROP, samples=(32, 32)),
        ),
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
        occupancy=SMOKE_OCCUPANCY,
        guided=SMOKE_GUIDED,
        vanilla=VanillaConfig(coarse_samples=8, fine_samples=16),
        grid=GridConfig(resolution=32, warmup_steps=4, update_every=4, march_steps=64),
        prop=SMOKE_PROP,
        ngp=NGPConfig(
            levels=2,
            log2_table_size=8,
            min_resolution=4,
            max_resolution=16,
            width=16,
            background_levels=2,
            background_log2_table_size=8,
            background_max_resolution=16,
            grid=GridConfig(
                resolution=32, warmup_steps=4, update_every=4, march_steps=64, levels=2
            ),
        ),
        ngp_leco=NGPLeCOConfig(occupancy=SMOKE_OCCUPANCY, guided=SMOKE_GUIDED),
        leco_prop=LeCOPropConfig(occupancy=SMOKE_OCCUPANCY, guided=SMOKE_GUIDED, prop=SMOKE_PROP),
        rays_per_device=64,
        main_steps=20,
        lr=5e-3,
        lr_final=5e-4,
    ),
}


# NGPConfig's keys that held ngp-leco's sampler before it had a section of its own (ngp_leco): an
# ngp-leco run saved their values in its own `guided` and `occupancy`.
RETIRED_NGP_KEYS = (
    "main_samples",
    "coarse_samples",
    "split",
    "dilate",
    "placement",
    "placement_in_phase1",
    "online_warmup",
    "occupancy_budget_share",
)


def upgrade_saved(data: dict) -> dict:
    """A resolved profile saved by a run of an earlier version (run.json, checkpoints, final/) in
    today's schema: the retired `ngp.*` sampler keys dropped and `ngp_leco` made from the run's
    own `occupancy` and `guided`, which are what it trained with whatever its method."""
    ngp = data.get("ngp")
    if "ngp_leco" in data or not isinstance(ngp, dict):
        return data
    upgraded = {**data, "ngp": {k: v for k, v in ngp.items() if k not in RETIRED_NGP_KEYS}}
    if "occupancy" in data and "guided" in data:
        upgraded["ngp_leco"] = {"occupancy": data["occupancy"], "guided": data["guided"]}
    return upgraded


def get_profile(name: str) -> Profile:
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}: choose one of {', '.join(PROFILES)}")
    return PROFILES[name]


def settings(profile: Profile) -> list[tuple[str, object, str]]:
    """Every setting of a profile by its dotted key (what `--set` and a job's overrides take), with
    its value there and its description."""
    rows: list[tuple[str, object, str]] = []

    def walk(section: BaseModel, prefix: str) -> None:
        for name, field in type(section).model_fields.items():
            value = getattr(section, name)
            if isinstance(value, BaseModel):
                walk(value, f"{prefix}{name}.")
            elif name != "name":
                rows.append((prefix + name, value, field.description or ""))

    walk(profile, "")
    return rows
