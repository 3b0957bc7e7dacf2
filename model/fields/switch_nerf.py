"""Switch-NeRF: a shared input layer, a top-1 gate over n homogeneous experts, shared heads."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.fields.encoding import FrequencyEncoding
from model.fields.experts import Expert, capacity_keep, dispatch, top1
from model.fields.heads import SceneHead
from model.fields.output import FieldOutput


class Gate(nn.Module):
    """Linear -> ReLU -> Linear -> LayerNorm -> bias-free projection to E logits, the projection in
    fp32."""

    def __init__(self, width: int, num_experts: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Linear(width, width), nn.ReLU(), nn.Linear(width, width), nn.LayerNorm(width)
        )
        self.proj = nn.Linear(width, num_experts, bias=False)

    def forward(self, h: Tensor) -> Tensor:
        z = self.body(h)
        with torch.autocast(device_type=z.device.type, enabled=False):
            return self.proj(z.float())  # routing decisions must not flip with bf16 rounding


class SwitchNeRF(nn.Module):
    def __init__(
        self,
        num_images: int,
        width: int = 256,
        num_experts: int = 8,
        expert_layers: int = 7,
        xyz_frequencies: int = 12,
        dir_frequencies: int = 4,
        appearance_dim: int = 48,
        capacity_factor: float | None = None,
        density_noise: float = 1.0,
    ):
        super().__init__()
        self.xyz_encoding = FrequencyEncoding(xyz_frequencies)
        self.dir_encoding = FrequencyEncoding(dir_frequencies)
        self.appearance = nn.Embedding(num_images, appearance_dim)
        # no activation: feeds gate and experts
        self.input_layer = nn.Linear(self.xyz_encoding.out_dim, width)
        self.gate = Gate(width, num_experts)
        self.experts = nn.ModuleList(Expert(width, expert_layers) for _ in range(num_experts))
        self.head = SceneHead(width, self.dir_encoding.out_dim, appearance_dim, density_noise)
        self.capacity_factor = capacity_factor

    def forward(self, xyz: Tensor, dirs: Tensor, image_index: Tensor) -> FieldOutput:
        h = self.input_layer(self.xyz_encoding(xyz))
        probs, index, chosen = top1(self.gate(h))
        keep = capacity_keep(
            index, chosen, len(self.experts), self.capacity_factor if self.training else None
        )
        # The top-1 probability scales the expert output (not renormalised), so the gate trains end
        # to end.
        mixed = torch.relu(dispatch(self.experts, h, index, keep) * chosen[:, None].to(h.dtype))
        _, sigma, rgb = self.head(mixed, self.dir_encoding(dirs), self.appearance(image_index))
        return FieldOutput(sigma, rgb, probs, index, keep)
