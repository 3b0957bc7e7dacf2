"""What the registry knows of a method without loading PyTorch: its name, labels, role, phases, and
what a run of it costs in memory. The API, the job schema and the dashboard read only this; the
training code behind it (a `Method` subclass, model/methods/base.py) is imported when a run or a
benchmark first asks for it."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from model.methods.costs import PhaseMemory
from model.profiles import Profile

if TYPE_CHECKING:
    from model.methods.base import Method


@dataclass(frozen=True)
class ReferenceTargets:
    """What the benchmark asks of a family's "ours" against its "reference" (None: no target, the
    ratio is still reported). The defaults are the paper's against vanilla Switch-NeRF."""

    rays_per_s: float | None = 2.5  # at least this many times the reference's rays/s
    best_sooner: float = 2.0  # reaches the reference's best PSNR this many times sooner
    samples_fraction: float | None = 0.25  # main-network samples per ray, at most this share
    memory_fraction: float | None = 0.5  # peak training memory, at most this share


# (profile, number of training images) -> each phase's memory needs
MemoryModel = Callable[[Profile, int], dict[str, PhaseMemory]]


@dataclass(frozen=True)
class MethodSpec:
    """One registry entry. `implementation` is the Method subclass, or "module:Class" to import it
    on first use. Calling the spec with a profile makes the method object
    (`get_method(name)(profile)`)."""

    name: str
    label: str  # the benchmark's row label
    implementation: str | type[Method]
    memory: MemoryModel
    # "ours": the method the benchmark reports speed-ups for; "reference": the unguided method its
    # equal-PSNR target and time ratios are measured against; "baseline": every other method.
    role: str = "baseline"
    # what "ours" must show against this method when it is the reference
    reference_targets: ReferenceTargets = ReferenceTargets()
    # the paper's table of quality and time for the family this method is "ours" of
    paper_table: str = "3"
    # Each phase and the profile setting that holds its step count, in training order.
    phase_steps: tuple[tuple[str, str], ...] = (("main", "main_steps"),)
    # an occupancy to score (the paper's Table 1) and to filter a point cloud with
    has_occupancy: bool = False
    colour: str | None = None  # in the benchmark's figures
    # The benchmark's target for the proposed method's occupancy size against this one's (a
    # fraction), if any.
    occupancy_size_target: float | None = None
    # The profile setting that stops a phase at a share of a wall-clock budget (phase -> dotted
    # key).
    budget_shares: tuple[tuple[str, str], ...] = ()
    # The profile setting of the fewest steps such a phase takes before its share stops it.
    budget_min_steps: tuple[tuple[str, str], ...] = ()
    # The main network the method trains: a benchmark compares the methods of one family (its
    # default is the family of the method whose role is "ours").
    family: str = "Switch-NeRF"
    # Sections of the profile the method reads from a section of its own (shared, own): its code
    # reads `shared`, and a job sets `own` (ngp-leco's sampler is `ngp_leco.guided`, not leco's).
    sections: tuple[tuple[str, str], ...] = ()

    @property
    def phases(self) -> tuple[str, ...]:
        return tuple(phase for phase, _ in self.phase_steps)

    def steps(self, profile: Profile, phase: str) -> int:
        return int(setting(profile, dict(self.phase_steps)[phase]))

    def budget_share(self, profile: Profile, phase: str) -> float | None:
        key = dict(self.budget_shares).get(phase)
        return None if key is None else setting(profile, key)

    def min_steps(self, profile: Profile, phase: str) -> int:
        key = dict(self.budget_min_steps).get(phase)
        return 0 if key is None else min(int(setting(profile, key)), self.steps(profile, phase))

    def load(self) -> type[Method]:
        if not isinstance(self.implementation, str):
            return self.implementation
        module, _, name = self.implementation.partition(":")
        return getattr(importlib.import_module(module), name)

    def __call__(self, profile: Profile) -> Method:
        method = self.load()(profile)
        method.spec = self
        return method

    def own_key(self, key: str) -> str:
        """The key a job sets for this method: a key of a shared section it reads from its own
        (`guided.split` for ngp-leco) becomes the own section's (`ngp_leco.guided.split`)."""
        for shared, own in self.sections:
            if key.startswith(f"{shared}."):
                return own + key[len(shared) :]
        return key

    def shared_key(self, key: str) -> str | None:
        """The own section this method reads in place of `key`'s shared one, if any."""
        return next((own for shared, own in self.sections if key.startswith(f"{shared}.")), None)


def setting(profile: Profile, key: str):
    """A profile value by its dotted key (`occupancy.steps`)."""
    value = profile
    for part in key.split("."):
        value = getattr(value, part)
    return value
