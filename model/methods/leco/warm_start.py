"""Warm start of LeCO's main phase from phase 1: the HMoE's scene experts, scene head, appearance
embeddings and O's input layer and body have exactly the shapes of Switch-NeRF's experts, head,
embeddings, input layer and gate body, and phase 1's background is the main phase's background. The
paper starts the main network from scratch and so throws phase 1's rendering away;
`guided.warm_start` keeps it."""

from __future__ import annotations

import torch
from torch import nn

from model.fields.background import BackgroundField
from model.fields.hmoe import HMoE
from model.fields.switch_nerf import SwitchNeRF


def module_pairs(field: SwitchNeRF, hmoe: HMoE) -> list[tuple[str, nn.Module, nn.Module]]:
    """(name, target in the main network, source in the HMoE) for every part whose shapes match."""
    gate = hmoe.gate
    pairs = [
        ("input_layer", field.input_layer, gate.input_layer),
        ("head", field.head, hmoe.scene_head),
        ("appearance", field.appearance, hmoe.appearance),
        ("gate.body.0", field.gate.body[0], gate.inner[0]),
        ("gate.body.2", field.gate.body[2], gate.inner[2]),
        ("gate.body.3", field.gate.body[3], gate.norm),
    ]
    pairs += [
        (f"experts.{i}", e, s) for i, (e, s) in enumerate(zip(field.experts, hmoe.scene_experts))
    ]
    return pairs


@torch.no_grad()
def warm_start_main(
    field: SwitchNeRF,
    background: BackgroundField,
    hmoe: HMoE,
    occupancy_background: BackgroundField | None,
    density: bool = True,
) -> list[str]:
    """Copy phase 1's weights into the main phase's networks where shapes match; returns what was
    copied. The gate projection takes O's scene-expert logits (O's last row is E_e's), so every
    point starts with the expert that rendered it in phase 1. Without `occupancy_background` the
    main background starts fresh: phase 1's learned to paint what the HMoE's foreground missed
    (guided.warm_start_background). With `density` False the head's density layer keeps its fresh
    initialisation: phase 1 left what its background painted (an aerial scene's ground)
    semi-transparent (guided.warm_start_density)."""
    fresh_sigma = {k: v.clone() for k, v in field.head.sigma.state_dict().items()}
    copied = []
    behind = (
        [] if occupancy_background is None else [("background", background, occupancy_background)]
    )
    for name, target, source in module_pairs(field, hmoe) + behind:
        src, dst = source.state_dict(), target.state_dict()
        if src.keys() == dst.keys() and all(src[k].shape == dst[k].shape for k in src):
            target.load_state_dict(src)
            copied.append(name)
    proj, logits = field.gate.proj.weight, hmoe.gate.output.weight[: hmoe.gate.num_scene_experts]
    if proj.shape == logits.shape:
        proj.copy_(logits)
        copied.append("gate.proj")
    if not density:
        field.head.sigma.load_state_dict(fresh_sigma)
        copied = [name if name != "head" else "head (colour only)" for name in copied]
    return copied
