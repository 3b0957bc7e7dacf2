"""The networks of each method built from a profile, and the parameter count of every component a method
trains, so a user sees what a scene will cost."""

from __future__ import annotations

from torch import nn

from model.fields.background import BackgroundField
from model.fields.hmoe import HMoE
from model.fields.switch_nerf import SwitchNeRF
from model.profiles import Profile

METHODS = ("leco", "switch", "grid")


def count(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())


def switch_nerf(profile: Profile, num_images: int) -> SwitchNeRF:
    n = profile.network
    return SwitchNeRF(num_images, n.width, n.num_experts, n.expert_layers, n.xyz_frequencies, n.dir_frequencies,
                      n.appearance_dim, n.capacity_factor, n.density_noise)


def hmoe(profile: Profile, num_images: int) -> HMoE:
    n = profile.network
    return HMoE(num_images, n.width, n.num_experts, n.expert_layers, n.xyz_frequencies, n.dir_frequencies,
                n.appearance_dim, profile.occupancy.homogeneous, n.density_noise,
                profile.occupancy.empty_gate_grad, profile.occupancy.gate_width,
                profile.occupancy.gate_relu_every_layer)


def background(profile: Profile, num_images: int) -> BackgroundField:
    b, n = profile.background, profile.network
    return BackgroundField(num_images, b.width, b.layers, dir_frequencies=n.dir_frequencies,
                           appearance_dim=n.appearance_dim, density_noise=n.density_noise)


def model_info(method: str, profile: Profile, num_images: int = 100) -> dict:
    """Per-component parameter counts (appearance embeddings for `num_images` images)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: choose one of {', '.join(METHODS)}")
    main = switch_nerf(profile, num_images)
    components = {
        "main.input_layer": count(main.input_layer),
        "main.gate": count(main.gate),
        "main.experts": count(main.experts),
        "main.heads": count(main.head),
        "main.appearance": count(main.appearance),
        "background": count(background(profile, num_images)),
    }
    if method == "leco":
        occ = hmoe(profile, num_images)
        components = {
            "occupancy_network": count(occ.gate),
            "phase1.scene_experts": count(occ.scene_experts),
            "phase1.scene_head": count(occ.scene_head),
            "phase1.empty_expert_and_head": count(occ.empty_expert, occ.empty_head),
            "phase1.appearance": count(occ.appearance),
            **components,
        }
    if method == "grid":
        components["grid_cells"] = profile.grid.resolution**3
    return {"method": method, "profile": profile.name, "num_images": num_images, "components": components,
            "total": sum(components.values())}


def format_model_info(info: dict) -> str:
    lines = [f"{info['method']} / {info['profile']} ({info['num_images']} appearance embeddings)"]
    width = max(len(k) for k in info["components"])
    lines += [f"  {k:<{width}}  {v:>12,}" for k, v in info["components"].items()]
    lines.append(f"  {'total':<{width}}  {info['total']:>12,}")
    return "\n".join(lines)
