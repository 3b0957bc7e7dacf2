"""Every method the service trains, by name: the CLI, the job schema, the API, the benchmark, the
dashboard and the docs read this table. Adding a method is a file in this package (a `Method`
subclass) and one line here (its MethodSpec: name, label, phases, memory model). Nothing here
imports PyTorch; a method's code is loaded when a run first asks for it."""

from __future__ import annotations

from collections.abc import Iterable

from model.methods import costs
from model.methods.spec import MethodSpec, ReferenceTargets

METHODS: dict[str, MethodSpec] = {}


def register(spec: MethodSpec) -> MethodSpec:
    """Adds a method; a name already taken by another method is refused."""
    known = METHODS.get(spec.name)
    if known is not None and known != spec:
        raise ValueError(
            f"method name {spec.name!r} is already registered (by {known.implementation!r})"
        )
    METHODS[spec.name] = spec
    return spec


def get_method(name: str) -> MethodSpec:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}: choose one of {', '.join(METHODS)}")
    return METHODS[name]


def family_of(name: str | None) -> list[str]:
    """The registered methods that train the same main network as `name` (all when None)."""
    family = METHODS[name].family if name in METHODS else None
    return [n for n, m in METHODS.items() if family is None or m.family == family]


def with_role(role: str, among: Iterable[str] | None = None) -> str | None:
    """The first registered method with this role ("ours", "reference"), among `among` when given
    (each family has its own pair), if any."""
    names = None if among is None else set(among)
    return next(
        (n for n, m in METHODS.items() if m.role == role and (names is None or n in names)), None
    )


register(
    MethodSpec(
        "leco",
        "S+Ours (LeCO)",
        "model.methods.leco.method:LeCOMethod",
        costs.leco,
        role="ours",
        phase_steps=(("occupancy", "occupancy.steps"), ("main", "main_steps")),
        has_occupancy=True,
        colour="#d62728",
        budget_shares=(("occupancy", "occupancy.budget_share"),),
        budget_min_steps=(("occupancy", "occupancy.min_steps"),),
    )
)
register(
    MethodSpec(
        "switch",
        "S-NeRF* (vanilla)",
        "model.methods.switch:SwitchNeRFMethod",
        costs.switch,
        role="reference",
        colour="#1f77b4",
    )
)
# The paper: 0.15M parameters instead of a 2M-cell grid, hence the size target.
register(
    MethodSpec(
        "grid",
        "S+Grid",
        "model.methods.grid:GridMethod",
        costs.grid,
        has_occupancy=True,
        colour="#2ca02c",
        occupancy_size_target=0.10,
    )
)
register(
    MethodSpec(
        "prop",
        "S+Prop",
        "model.methods.prop:ProposalMethod",
        costs.prop,
        has_occupancy=True,
        colour="#8c564b",
    )
)
# LeCO decides where not to look, proposals decide where to look (model/methods/leco_prop.py).
LECO_PROP_SECTIONS = (
    ("occupancy", "leco_prop.occupancy"),
    ("guided", "leco_prop.guided"),
    ("prop", "leco_prop.prop"),
)
register(
    MethodSpec(
        "leco-prop",
        "S+LeCO+Prop",
        "model.methods.leco_prop:LeCOPropMethod",
        costs.leco_prop,
        phase_steps=(("occupancy", "occupancy.steps"), ("main", "main_steps")),
        has_occupancy=True,
        colour="#ff7f0e",
        budget_shares=(("occupancy", "occupancy.budget_share"),),
        budget_min_steps=(("occupancy", "occupancy.min_steps"),),
        sections=LECO_PROP_SECTIONS,
    )
)
# The hash-grid family (the paper's Appendix C, Table 6): Instant-NGP's field under each sampler,
# with its own pair of "ours" and "reference".
register(
    MethodSpec(
        "ngp",
        "NGP",
        "model.methods.ngp:NGPMethod",
        costs.ngp,
        role="reference",
        # Table 6 asks NGP+Ours for NGP's PSNR sooner; rays/s, samples and memory are reported
        reference_targets=ReferenceTargets(
            rays_per_s=None, best_sooner=1.0, samples_fraction=None, memory_fraction=None
        ),
        has_occupancy=True,
        colour="#9467bd",
        family="Instant-NGP",
    )
)
register(
    MethodSpec(
        "ngp-leco",
        "NGP+Ours (LeCO)",
        "model.methods.ngp:NGPLeCOMethod",
        costs.ngp_leco,
        role="ours",
        paper_table="6",
        phase_steps=(("occupancy", "occupancy.steps"), ("main", "main_steps")),
        has_occupancy=True,
        colour="#e377c2",
        budget_shares=(("occupancy", "occupancy.budget_share"),),
        budget_min_steps=(("occupancy", "occupancy.min_steps"),),
        family="Instant-NGP",
        sections=(("occupancy", "ngp_leco.occupancy"), ("guided", "ngp_leco.guided")),
    )
)
register(
    MethodSpec(
        "ngp-prop",
        "NGP+Prop",
        "model.methods.ngp:NGPProposalMethod",
        costs.ngp_prop,
        has_occupancy=True,
        colour="#17becf",
        family="Instant-NGP",
    )
)
register(
    MethodSpec(
        "ngp-leco-prop",
        "NGP+LeCO+Prop",
        "model.methods.ngp:NGPLeCOPropMethod",
        costs.ngp_leco_prop,
        phase_steps=(("occupancy", "occupancy.steps"), ("main", "main_steps")),
        has_occupancy=True,
        colour="#bcbd22",
        budget_shares=(("occupancy", "occupancy.budget_share"),),
        budget_min_steps=(("occupancy", "occupancy.min_steps"),),
        family="Instant-NGP",
        sections=LECO_PROP_SECTIONS,
    )
)
