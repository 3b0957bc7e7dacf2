"""What a method is: the one place that knows how a run of it builds its networks, what each phase
trains and samples, and what it exports. The training loop, evaluation, benchmark, API and dashboard
talk to this interface and never compare method names.

A method object is made from the resolved profile (`method = get_method(name)(profile)`); that alone
is cheap and answers the static questions (phases, parameter counts, memory needs, benchmark sweep).
`build` makes the networks of one run; the object then also holds that run's non-network state (an
occupancy grid, a frozen predictor), which it checkpoints through `state_dict` / `load_state_dict`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

import torch
from torch import Tensor, nn

from model.fields.background import BackgroundField
from model.fields.switch_nerf import SwitchNeRF
from model.methods.costs import PhaseMemory, SweepPoint
from model.methods.main_phase import MainRender, main_loss
from model.methods.stages import stage
from model.profiles import Profile
from model.render.noise import Noise
from model.render.volume import Rendered
from model.scenes.rays import RayBatch

# An estimator's answer (model/estimators/base.py Estimator.occupied): world points (N, 3) on any
# device -> bool (N,) on the estimator's own device.
Occupied = Callable[[Tensor], Tensor]


class Entry(Protocol):
    """What a method reads off its registry entry (MethodSpec, model/methods/spec.py, which imports
    this module's Method: a Protocol here keeps the two modules out of a cycle)."""

    @property
    def name(self) -> str: ...

    @property
    def phases(self) -> tuple[str, ...]: ...

    def steps(self, profile: Profile, phase: str) -> int: ...

    def budget_share(self, profile: Profile, phase: str) -> float | None: ...

    def min_steps(self, profile: Profile, phase: str) -> int: ...

    @property
    def memory(self) -> Callable[[Profile, int], dict[str, PhaseMemory]]: ...


def count(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def switch_nerf(profile: Profile, num_images: int) -> SwitchNeRF:
    n = profile.network
    return SwitchNeRF(
        num_images,
        width=n.width,
        num_experts=n.num_experts,
        expert_layers=n.expert_layers,
        xyz_frequencies=n.xyz_frequencies,
        dir_frequencies=n.dir_frequencies,
        appearance_dim=n.appearance_dim,
        capacity_factor=n.capacity_factor,
        density_noise=n.density_noise,
    )


def background(profile: Profile, num_images: int) -> BackgroundField:
    b, n = profile.background, profile.network
    return BackgroundField(
        num_images,
        width=b.width,
        layers=b.layers,
        dir_frequencies=n.dir_frequencies,
        appearance_dim=n.appearance_dim,
        density_noise=n.density_noise,
        sky_at_infinity=b.sky_at_infinity,
    )


@dataclass(frozen=True)
class Step:
    """What one training step works on besides the networks."""

    phase: str
    rays: RayBatch  # this rank's share of the step's rays, on the run's device
    noise: Noise | None  # this rank's draws; None: deterministic (perturb off)
    progress: float  # of the phase, in [0, 1] (model/methods/schedules.py)
    phase_step: int  # steps of this phase done before this one
    seed: int  # the run's, for any draw that must be the same on every rank (a grid's update)


class Networks(nn.Module):
    """A run's trainable networks, named by the method that built them (checkpoints keep these
    names)."""

    def __getattr__(self, name: str) -> Any:
        # Submodules are the method's to name; typed as Any so each method reads its own without
        # casts.
        return super().__getattr__(name)


class Method:
    """A method's training code. Its name, labels, phases and memory model are its registry entry's
    (model/methods/spec.py), set as `spec` when the registry makes the object."""

    spec: Entry

    def __init__(self, profile: Profile):
        self.profile = profile

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def phases(self) -> tuple[str, ...]:
        return self.spec.phases

    # ----- what a run of it costs, before it runs
    # ---------------------------------------------------------
    def build(self, num_images: int, aabb: Tensor) -> Networks:
        """The main phase's networks (`field` and `background`), which every method has."""
        models = Networks()
        models.field, models.background = self.main_networks(num_images, aabb)
        return models

    def main_networks(self, num_images: int, aabb: Tensor) -> tuple[nn.Module, nn.Module]:
        """The network the main phase trains and the background beside it: Switch-NeRF and
        Mega-NeRF's background, unless a family of methods (model/methods/ngp.py) says otherwise."""
        return switch_nerf(self.profile, num_images), background(self.profile, num_images)

    def components(self, num_images: int) -> dict[str, int]:
        """Parameter count of every component a run trains (model_info)."""
        return self.main_components(num_images)

    def main_components(self, num_images: int) -> dict[str, int]:
        """The main networks' parameter counts, built on the meta device."""
        with torch.device("meta"):
            main, behind = (
                switch_nerf(self.profile, num_images),
                background(self.profile, num_images),
            )
        return {
            "main.input_layer": count(main.input_layer),
            "main.gate": count(main.gate),
            "main.experts": count(main.experts),
            "main.heads": count(main.head),
            "main.appearance": count(main.appearance),
            "background": count(behind),
        }

    def memory(self, num_images: int) -> dict[str, PhaseMemory]:
        return self.spec.memory(self.profile, num_images)

    def sweep(self) -> list[SweepPoint]:
        """Sampling budgets around the profile's own for `leco bench --sweep` (none: not swept)."""
        return []

    # ----- a run
    # --------------------------------------------------------------------------------------
    def to(self, device: torch.device) -> "Method":
        """Moves non-network state (a grid, a predictor) to the run's device."""
        return self

    def phase_steps(self, phase: str) -> int:
        return self.spec.steps(self.profile, phase)

    def budget_share(self, phase: str) -> float | None:
        """The share of a wall-clock budget the phase stops at; None: whatever the phases before it
        left."""
        return self.spec.budget_share(self.profile, phase)

    def budget_min_steps(self, phase: str) -> int:
        """The fewest steps a phase with a budget share takes before the share stops it."""
        return self.spec.min_steps(self.profile, phase)

    def phase_lr(self, phase: str) -> tuple[float, float | None]:
        """(start, final) learning rate of the phase; the schedule decays log-linearly between
        them."""
        return self.profile.lr, self.profile.lr_final

    def adam_options(self, phase: str) -> dict:
        """Adam's betas and eps for the phase, where the method wants other than PyTorch's."""
        return {}

    def distortion_weight(self) -> float:
        """The main phase's weight on mip-NeRF 360's distortion loss (0: none)."""
        return 0.0

    def lr_scales(self, models: Networks, phase: str) -> list[tuple[nn.Module, float]]:
        """Networks the phase trains at a multiple of its learning rate (the rest: 1)."""
        return []

    def trained_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        """The networks the phase trains and renders with (their appearance embeddings are the ones
        the validation protocol fits)."""
        return [models.field, models.background]

    def compiled_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        """The networks a run with `compile` compiles for the phase: those it trains, each network
        of a list on its own (a list is not called)."""
        modules: list[nn.Module] = []
        for module in self.trained_modules(models, phase):
            modules += list(module) if isinstance(module, nn.ModuleList) else [module]
        return modules

    def extra_parameters(self, models: Networks, phase: str) -> list[nn.Parameter]:
        """Parameters the phase's optimizer also steps, outside `trained_modules`."""
        return []

    def start_phase(
        self,
        models: Networks,
        phase: str,
        fresh: bool,
        device: torch.device,
        log: Callable[[str], None],
    ) -> None:
        """Sets up the phase (frozen parts, estimators); `fresh` when it begins now rather than on a
        resume."""

    def lr_ramp_steps(self, phase: str) -> int:
        return 0

    def step(self, models: Networks, step: Step) -> tuple[Tensor, dict]:
        """One training step's loss and its parts (floats)."""
        render = self.render_main(models, step.rays, step.noise, step.phase_step)
        with stage("losses"):
            return main_loss(
                render,
                step.rays,
                self.profile.balance_weight,
                self.profile.guided.coarse_samples,
                self.distortion_weight(),
            )

    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        """The main phase's render; `phase_step` is None outside training (validation,
        evaluation)."""
        raise NotImplementedError

    def render(self, models: Networks, phase: str, rays: RayBatch) -> Rendered:
        """A deterministic render of `phase`'s networks as they are (train or eval mode), keeping
        autograd."""
        return self.render_main(models, rays, None, None).rendered

    def occupancy(self, models: Networks, phase: str) -> Occupied | None:
        """The occupancy to score while training (periodic evaluation); None: nothing is being
        learned."""
        return None

    def final_occupancy(self, models: Networks) -> Occupied | None:
        """The occupancy a finished run scores and exports (Table 1, the point cloud's filter)."""
        return None

    def decision_rules(self, models: Networks) -> dict[str, Occupied]:
        """Other decisions of the final occupancy to score beside `final_occupancy`, by name (LeCO:
        O's top-1, the paper's rule, when it samples with a threshold)."""
        return {}

    def point_cloud_samples(self) -> int:
        """Coarse samples per ray of the exported point cloud."""
        return self.profile.vanilla.coarse_samples

    def state_dict(self) -> dict | None:
        """Non-network state that checkpoints keep (networks are in `Networks.state_dict`)."""
        return None

    def load_state_dict(self, state: dict | None) -> None:
        pass

    def save_final(self, final: Path) -> None:
        """Extra files of a finished run (LeCO's occupancy network on its own)."""

    def load_final(self, models: Networks, final: Path, device: torch.device) -> None:
        pass

    def summary_occupancy(self, final: Path, main: list[dict], first: list[dict]) -> dict:
        """The occupancy row of a run's summary: its size and how much it keeps (`main`/`first`: the
        metrics rows of the main phase and of any phase before it)."""
        return {}


def mean_of(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if r.get(key) is not None]
    return sum(values) / len(values) if values else None


def method_state(saved: dict) -> dict | None:
    """A checkpoint's non-network method state (Method.state_dict). Checkpoints written before the
    methods had a home kept the only such state, the grid's, under "grid"; they still load."""
    return saved["method"] if "method" in saved else saved.get("grid")
