"""What a benchmark trains: the three methods, and the ablations of the paper's Tables 4 and 5. Every variant
is a TrainConfig method plus profile overrides, so the main network, background, batch, optimiser and schedule
are the profile's for all of them and only the sampling (and, for ablations, the occupancy phase) differs."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Variant:
    name: str
    method: str
    label: str  # as the paper's tables name it
    overrides: dict = field(default_factory=dict)
    ablation: bool = False
    ladder: bool = False  # a rung of the ablation ladder (issue 16); like an ablation, not a compared method


METHODS = {
    "leco": Variant("leco", "leco", "S+Ours (LeCO)"),
    "switch": Variant("switch", "switch", "S-NeRF* (vanilla)"),
    "grid": Variant("grid", "grid", "S+Grid"),
}

# Table 4 trains without the density loss (both MoEs); Table 5 compares LeCO with and without it.
ABLATIONS = {
    "leco-homogeneous": Variant("leco-homogeneous", "leco", "Homo. MoE, no L_d",
                                {"occupancy.homogeneous": True, "occupancy.w_d": 0.0}, ablation=True),
    "leco-no-density-loss": Variant("leco-no-density-loss", "leco", "Heter. (HMoE), no L_d",
                                    {"occupancy.w_d": 0.0}, ablation=True),
}


# The paper's formulation at the profile's sizes: every setting issue 16 added, back at the paper's value.
PAPER_FORMULATION = {
    "occupancy.lr_final": None, "occupancy.w_g_final": None, "occupancy.w_v": 0.0,
    "occupancy.empty_gate_grad": True, "guided.jitter": False, "guided.dilate": 0, "guided.fallback": False,
    "guided.warm_start": False, "guided.split": 8, "guided.empty_threshold": None,
}

# The ablation ladder: from the paper's formulation, one change at a time (cumulative) up to the `cpu`
# defaults. The last rung is the profile's defaults, so the `leco` run itself stands for it (a test checks
# that the changes add up to the `cpu` profile). Measured in docs/BENCHMARKS.md.
RUNGS: list[tuple[str, str, dict]] = [
    ("leco-paper", "paper's formulation", {}),
    ("leco-rung-empty-gate", "+ E_e gate detached from L_r", {"occupancy.empty_gate_grad": False}),
    ("leco-rung-warm-start", "+ warm start of the main phase", {"guided.warm_start": True}),
    ("leco-rung-fallback", "+ fallback for rays with nothing kept", {"guided.fallback": True}),
    ("leco-rung-jitter", "+ jittered O queries", {"guided.jitter": True}),
    ("leco-rung-dilate-1", "+ dilation by 1 bin, split 8 -> 4", {"guided.dilate": 1, "guided.split": 4}),
    ("leco-rung-dilate-2", "+ dilation by 2 bins", {"guided.dilate": 2}),
    ("leco", "+ keep p(E_e) < 0.9, not O's top-1 (the cpu defaults)", {"guided.empty_threshold": 0.9}),
]


def rung_overrides() -> list[dict]:
    """Each rung's overrides of the profile: the paper's formulation plus every change up to that rung."""
    out, overrides = [], dict(PAPER_FORMULATION)
    for _, _, change in RUNGS:
        overrides = {**overrides, **change}
        out.append(dict(overrides))
    return out


def ladder() -> list[Variant]:
    """The rungs to train besides `leco` (the last rung)."""
    return [Variant(name, "leco", label, overrides, ablation=True, ladder=True)
            for (name, label, _), overrides in zip(RUNGS[:-1], rung_overrides()[:-1])]


def select(methods: list[str], ablation: bool, with_ladder: bool = False) -> list[Variant]:
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"--methods: unknown method(s) {', '.join(unknown)}: choose from {', '.join(METHODS)}")
    if not methods and not ablation:
        raise ValueError("--methods is empty and --ablation is off: nothing to benchmark")
    chosen = [METHODS[m] for m in dict.fromkeys(methods)]
    if ablation:
        chosen += list(ABLATIONS.values())
        if "leco" not in methods:
            chosen.append(METHODS["leco"])  # the full method (HMoE + L_d) is the ablations' reference row
    if with_ladder:
        chosen += ladder()
        if "leco" not in [v.name for v in chosen]:
            chosen.append(METHODS["leco"])  # the last rung: the profile's defaults
    return chosen
