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


def select(methods: list[str], ablation: bool) -> list[Variant]:
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
    return chosen
