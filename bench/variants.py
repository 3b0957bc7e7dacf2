"""What a benchmark trains: the registered methods (model/methods), and the ablations of the paper's
Tables 4 and 5. Every variant is a TrainConfig method plus profile overrides, so the main network,
background, batch, optimiser and schedule are the profile's for all of them and only the sampling
(and, for ablations, the occupancy phase) differs."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from model.methods import METHODS as REGISTRY
from model.methods import get_method, with_role
from model.profiles import Profile
from workers.config import parse_overrides


@dataclass(frozen=True)
class Variant:
    name: str
    method: str
    label: str  # as the paper's tables name it
    overrides: dict = field(default_factory=dict)
    ablation: bool = False
    ladder: bool = False  # a rung of the ablation ladder; like an ablation, not a compared method
    # another sampling budget of `method` (`--sweep`); like an ablation, not a compared method
    sweep: bool = False
    table: str = ""  # the paper's ablation table this variant is a row of


def method_variants() -> dict[str, Variant]:
    """Every registered method as a benchmark variant of its own name and label."""
    return {name: Variant(name, name, m.label) for name, m in REGISTRY.items()}


# Table 4 trains without the density loss (both MoEs); Table 5 compares LeCO with and without it.
# Table 7 puts a 256^3 grid beside the 128^3 one and LeCO; Table 9 sizes the empty-space expert
# (identity is LeCO's own).
ABLATIONS = {
    "leco-homogeneous": Variant(
        "leco-homogeneous",
        "leco",
        "Homo. MoE, no L_d",
        {"occupancy.homogeneous": True, "occupancy.w_d": 0.0},
        ablation=True,
        table="4/5",
    ),
    "leco-no-density-loss": Variant(
        "leco-no-density-loss",
        "leco",
        "Heter. (HMoE), no L_d",
        {"occupancy.w_d": 0.0},
        ablation=True,
        table="4/5",
    ),
    "grid-256": Variant(
        "grid-256", "grid", "Grid-256", {"grid.resolution": 256}, ablation=True, table="7"
    ),
    "leco-empty-4-layer": Variant(
        "leco-empty-4-layer",
        "leco",
        "E_e: 4-layer MLP",
        {"occupancy.empty_expert_layers": 4},
        ablation=True,
        table="9",
    ),
    "leco-empty-homogeneous": Variant(
        "leco-empty-homogeneous",
        "leco",
        "E_e: homogeneous (a scene expert)",
        {"occupancy.homogeneous": True},
        ablation=True,
        table="9",
    ),
}
# The rows each ablation table compares against: besides its variants, these methods' own runs.
TABLE_REFERENCES = {"4/5": ("ours",), "7": ("grid", "ours"), "9": ("ours",)}


# The paper's formulation at the profile's sizes: every setting added beyond it, back at the paper's
# value.
PAPER_FORMULATION = {
    "occupancy.lr_final": None,
    "occupancy.w_g_final": None,
    "occupancy.w_v": 0.0,
    "occupancy.empty_gate_grad": True,
    "guided.jitter": False,
    "guided.dilate": 0,
    "guided.fallback": False,
    "guided.warm_start": False,
    "guided.split": 8,
    "guided.empty_threshold": None,
    "guided.online": False,
    "guided.warm_start_background": True,
    "guided.online_free_opacity": 0.0,
    "guided.fallback_topk": 0,
    "guided.placement": False,
    "guided.placement_in_phase1": False,
    "guided.placement_padding": 0.01,
    "occupancy.budget_share": 0.25,
    "occupancy.gate_relu_every_layer": False,
}

# The ablation ladder: from the paper's formulation, one change at a time (cumulative) up to the
# `cpu` defaults. The last rung is the profile's defaults, so the `leco` run itself stands for it (a
# test checks that the changes add up to the `cpu` profile). Measured in docs/EXPERIMENTS.md.
RUNGS: list[tuple[str, str, dict]] = [
    ("leco-paper", "paper's formulation", {}),
    ("leco-rung-empty-gate", "+ E_e gate detached from L_r", {"occupancy.empty_gate_grad": False}),
    ("leco-rung-warm-start", "+ warm start of the main phase", {"guided.warm_start": True}),
    ("leco-rung-fallback", "+ fallback for rays with nothing kept", {"guided.fallback": True}),
    ("leco-rung-jitter", "+ jittered O queries", {"guided.jitter": True}),
    ("leco-rung-split-4", "+ kept bins split in 4, not 8", {"guided.split": 4}),
    ("leco-rung-dilate-1", "+ dilation by 1 bin", {"guided.dilate": 1}),
    ("leco-rung-dilate-2", "+ dilation by 2 bins", {"guided.dilate": 2}),
    ("leco-rung-threshold", "+ keep p(E_e) < 0.9, not O's top-1", {"guided.empty_threshold": 0.9}),
    ("leco-rung-online", "+ O keeps learning in the main phase", {"guided.online": True}),
    (
        "leco-rung-fresh-background",
        "+ the main phase's background starts fresh",
        {"guided.warm_start_background": False},
    ),
    (
        "leco-rung-free-opacity",
        "+ no bin called free behind a semi-transparent foreground",
        {"guided.online_free_opacity": 0.5},
    ),
    (
        "leco-rung-topk",
        "+ O's 2 best bins for a ray with nothing kept",
        {"guided.fallback_topk": 2},
    ),
    (
        "leco-rung-placement",
        "+ O places 21 samples per hit ray, learnt in both phases",
        {"guided.placement": True, "guided.placement_in_phase1": True, "guided.main_samples": 21},
    ),
    (
        "leco-rung-placement-dilate-1",
        "+ dilation back to 1 bin under placement",
        {"guided.dilate": 1},
    ),
    (
        "leco-rung-padding",
        "+ placement padding 0.001, not 0.01",
        {"guided.placement_padding": 0.001},
    ),
    (
        "leco",
        "+ phase 1 stops at 15% of a budget, not 25% (the cpu defaults)",
        {"occupancy.budget_share": 0.15},
    ),
]


def rung_overrides() -> list[dict]:
    """Each rung's overrides of the profile: the paper's formulation plus every change up to that
    rung."""
    out, overrides = [], dict(PAPER_FORMULATION)
    for _, _, change in RUNGS:
        overrides = {**overrides, **change}
        out.append(dict(overrides))
    return out


def rung(name: str) -> dict:
    """One rung's overrides: the paper's formulation and every change of the ladder up to it."""
    names = [n for n, _, _ in RUNGS]
    return rung_overrides()[names.index(name)]


# Earlier defaults, by the date they were the defaults, so a suite can judge a default against the
# one it replaced in one command (`--methods leco,leco-2026-11-25`). Each is the method at the
# `cpu` profile with the values it had then; the code is today's.
CONFIGURATIONS: dict[str, Variant] = {
    # before 9f50ef1 and dc86ef6: no placement head, dilation 2, the warm-started background, no
    # free-opacity rule or top-2 fallback, phase 1 at 25% of a budget: the ladder's online rung
    "leco-2026-11-25": Variant(
        "leco-2026-11-25",
        "leco",
        "LeCO, defaults of 2026-11-25",
        rung("leco-rung-online"),
    ),
    # before 2602b02: ngp-leco read LeCO's phase 1 and sampler (placement learnt in both phases,
    # 16 bins split in 4, online from step 500, phase 1 at 15%) with 42 placed samples (e661066)
    "ngp-leco-2026-11-27": Variant(
        "ngp-leco-2026-11-27",
        "ngp-leco",
        "NGP+LeCO, defaults of 2026-11-27",
        {
            "ngp_leco.occupancy.budget_share": 0.15,
            "ngp_leco.guided.coarse_samples": 16,
            "ngp_leco.guided.split": 4,
            "ngp_leco.guided.placement": True,
            "ngp_leco.guided.placement_in_phase1": True,
            "ngp_leco.guided.online_warmup": 500,
            "ngp_leco.guided.online_surface_points": False,
        },
    ),
}


def ladder() -> list[Variant]:
    """The rungs to train besides `leco` (the last rung)."""
    return [
        Variant(name, "leco", label, overrides, ablation=True, ladder=True)
        for (name, label, _), overrides in zip(RUNGS[:-1], rung_overrides()[:-1])
    ]


def sweep(methods: list[str], profile_of: Callable[[str], Profile]) -> list[Variant]:
    """`--sweep` (item 6): each method at the sampling budgets its own file names (Method.sweep),
    around its resolved profile's (`profile_of(method)`), whose own run is the middle point, so PSNR
    can be read against samples per ray and rays/s."""
    return [
        Variant(
            f"{m}-sweep-{p.tag}",
            m,
            f"{get_method(m).label}, {p.text}",
            # as the job sets them: a method that reads a section from its own is swept there
            {get_method(m).own_key(key): value for key, value in p.overrides.items()},
            ablation=True,
            sweep=True,
        )
        for m in methods
        for p in get_method(m)(profile_of(m)).sweep()
    ]


def _ours() -> str:
    ours = with_role("ours")
    if ours is None:
        raise ValueError(
            "no registered method has the role 'ours': the ablations and the ladder compare to it"
        )
    return ours


LEVER = "+"  # `leco+occupancy.min_steps=900`: a method with settings of its own, beside the method


def lever(name: str, known: dict[str, Variant]) -> Variant | None:
    """`METHOD+KEY=VALUE[+KEY=VALUE...]`: a known method or configuration with these settings on top
    of its own, so a lever and its baseline train in one command (`--methods leco,leco+KEY=VALUE`),
    seed by seed in turn. None if the name has no `+`; an error naming what is wrong otherwise."""
    base, sep, rest = name.partition(LEVER)
    if not sep:
        return None
    if base not in known:
        raise ValueError(
            f"--methods {name!r}: unknown method {base!r}: choose from {', '.join(known)}"
        )
    items = rest.split(LEVER)
    if not all("=" in item for item in items):
        raise ValueError(
            f"--methods {name!r}: after {base!r} expected KEY=VALUE settings joined by "
            f"'{LEVER}', e.g. {base}+occupancy.min_steps=900"
        )
    try:
        settings = parse_overrides(items)
    except ValueError as error:
        raise ValueError(f"--methods {name!r}: {error}") from None
    origin = known[base]
    label = ", ".join(f"{key}={value}" for key, value in settings.items())
    return Variant(
        name, origin.method, f"{origin.label}, {label}", {**origin.overrides, **settings}
    )


def select(
    methods: list[str],
    ablation: bool,
    with_ladder: bool = False,
    sweep_profile: Callable[[str], Profile] | None = None,
) -> list[Variant]:
    known = {**method_variants(), **CONFIGURATIONS}
    known.update({m: v for m in methods if (v := lever(m, known)) is not None})
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ValueError(
            f"--methods: unknown method(s) {', '.join(unknown)}: choose from {', '.join(known)}"
        )
    if not methods and not ablation:
        raise ValueError("--methods is empty and --ablation is off: nothing to benchmark")
    chosen = [known[m] for m in dict.fromkeys(methods)]
    if ablation:
        chosen += list(ABLATIONS.values())
        for name in dict.fromkeys(n for refs in TABLE_REFERENCES.values() for n in refs):
            name = _ours() if name == "ours" else name
            if name not in [v.name for v in chosen]:
                chosen.append(known[name])  # a table's reference row (the full method: HMoE + L_d)
    if with_ladder:
        ours = _ours()
        chosen += ladder()
        if ours not in [v.name for v in chosen]:
            chosen.append(known[ours])  # the last rung: the profile's defaults
    if sweep_profile is not None:
        chosen += sweep([m for m in dict.fromkeys(methods) if m in REGISTRY], sweep_profile)
    return chosen
