"""LeCO's Heterogeneous Mixture of Experts: the occupancy network O gates n scene experts and one
tiny empty-space expert E_e (an identity layer with its own head). A point sent to E_e is
unoccupied."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from model.fields.encoding import FrequencyEncoding
from model.fields.experts import Expert, dispatch, top1
from model.fields.heads import EmptyHead, SceneHead
from model.fields.output import FieldOutput


class OccupancyNetwork(nn.Module):
    """O: input layer, 2 inner layers, LayerNorm, output layer of n + 1 gate logits (the last is
    E_e). Its input layer's output also feeds the experts, as Switch-NeRF's shared input layer
    does."""

    def __init__(
        self,
        num_scene_experts: int = 8,
        width: int = 256,
        xyz_frequencies: int = 12,
        inner_width: int | None = None,
        relu_every_layer: bool = False,
        placement_head: bool = False,
    ):
        """inner_width: O's own layers after the shared input layer (None: `width`, the paper's).
        relu_every_layer: O's path also applies a ReLU after the shared input layer and after its
        second inner layer; without it (the paper's layer list as we read it) the input layer and
        the first inner layer compose to one linear map, so O has a single hidden nonlinearity. The
        experts' input is unchanged. placement_head: one more output unit, a density that says where
        along a ray the main network's weight lies (trained by the interlevel loss while O guides
        the main phase; model/estimators/placement.py)."""
        super().__init__()
        inner = inner_width or width
        self.relu_every_layer = relu_every_layer
        self.xyz_encoding = FrequencyEncoding(xyz_frequencies)
        self.input_layer = nn.Linear(self.xyz_encoding.out_dim, width)
        self.inner = nn.Sequential(nn.Linear(width, inner), nn.ReLU(), nn.Linear(inner, inner))
        self.norm = nn.LayerNorm(inner)
        self.output = nn.Linear(inner, num_scene_experts + 1)
        self.placement = nn.Linear(inner, 1) if placement_head else None
        self.num_scene_experts = num_scene_experts

    @property
    def config(self) -> dict:
        """The constructor's arguments, to rebuild O alone (model/estimators/occupancy.py)."""
        return {
            "num_scene_experts": self.num_scene_experts,
            "width": self.input_layer.out_features,
            "xyz_frequencies": len(self.xyz_encoding.freqs),
            "inner_width": self.norm.normalized_shape[0],
            "relu_every_layer": self.relu_every_layer,
            "placement_head": self.placement is not None,
        }

    @property
    def empty_index(self) -> int:
        return self.num_scene_experts

    def trunk(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        """The shared input layer's output h (the experts' input) and O's own features z."""
        h = self.input_layer(self.xyz_encoding(xyz))
        # functional, so the state dict's keys do not depend on the setting
        if self.relu_every_layer:
            return h, self.norm(torch.relu(self.inner(torch.relu(h))))
        return h, self.norm(self.inner(h))

    def features_and_logits(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        h, z = self.trunk(xyz)
        with torch.autocast(device_type=z.device.type, enabled=False):
            return h, self.output(z.float())

    def forward(self, xyz: Tensor) -> Tensor:
        return self.features_and_logits(xyz)[1]

    def query(self, xyz: Tensor) -> tuple[Tensor, Tensor | None]:
        """Gate logits and, with a placement head, its density >= 0 (softplus(x - 1), as the main
        network's)."""
        _, z = self.trunk(xyz)
        with torch.autocast(device_type=z.device.type, enabled=False):
            z = z.float()
            sigma = (
                None if self.placement is None else F.softplus(self.placement(z).squeeze(-1) - 1.0)
            )
            return self.output(z), sigma

    def decision_logit(self, logits: Tensor, empty_threshold: float | None = None) -> Tensor:
        """A logit that is positive exactly where `decide` keeps the point: log-odds of occupancy (1
        - p(E_e)) shifted by the threshold (top-1 without one: the best scene expert's logit against
        E_e's)."""
        logits = logits.float()
        empty = self.empty_index
        scene = torch.cat([logits[:, :empty], logits[:, empty + 1 :]], dim=-1)
        if empty_threshold is None:
            return scene.max(dim=-1).values - logits[:, empty]
        occupied = torch.logsumexp(scene, dim=-1) - logits[:, empty]  # log((1 - p_e) / p_e)
        return occupied - torch.log(torch.tensor((1 - empty_threshold) / empty_threshold))

    @torch.no_grad()
    def occupied(self, xyz: Tensor, empty_threshold: float | None = None) -> Tensor:
        """True where the top-1 gate is a scene expert (the paper); with a threshold, where E_e's
        gate probability is below it (a threshold above 0.5 keeps a superset of the top-1 decision's
        points)."""
        return self.decide(self(xyz), empty_threshold)

    def decide(self, logits: Tensor, empty_threshold: float | None = None) -> Tensor:
        """`occupied` from logits already computed (O learning online computes them with
        gradient)."""
        logits = logits.detach()
        if empty_threshold is None:
            return logits.argmax(dim=-1) != self.empty_index
        return torch.softmax(logits.float(), dim=-1)[:, self.empty_index] < empty_threshold


class HMoE(nn.Module):
    def __init__(
        self,
        num_images: int,
        width: int = 256,
        num_scene_experts: int = 8,
        expert_layers: int = 7,
        xyz_frequencies: int = 12,
        dir_frequencies: int = 4,
        appearance_dim: int = 48,
        homogeneous: bool = False,
        density_noise: float = 1.0,
        empty_gate_grad: bool = True,
        gate_width: int | None = None,
        gate_relu_every_layer: bool = False,
        empty_expert_layers: int = 0,
        placement_head: bool = False,
    ):
        """homogeneous=True makes E_e a full expert (the paper's ablation) instead of an identity
        layer; empty_expert_layers=N an N-layer one (Table 9's 4-layer row). empty_gate_grad=False
        detaches E_e's gate value where it scales E_e's output, so the rendering loss cannot lock a
        visible surface into E_e by raising that gate; L_g and L_d still train it."""
        super().__init__()
        self.empty_gate_grad = empty_gate_grad
        self.gate = OccupancyNetwork(
            num_scene_experts,
            width,
            xyz_frequencies,
            gate_width,
            gate_relu_every_layer,
            placement_head,
        )
        self.dir_encoding = FrequencyEncoding(dir_frequencies)
        self.appearance = nn.Embedding(num_images, appearance_dim)
        self.scene_experts = nn.ModuleList(
            Expert(width, expert_layers) for _ in range(num_scene_experts)
        )
        self.scene_head = SceneHead(width, self.dir_encoding.out_dim, appearance_dim, density_noise)
        layers = expert_layers if homogeneous else empty_expert_layers
        self.empty_expert = Expert(width, layers) if layers else nn.Identity()
        self.empty_head = EmptyHead(width, density_noise)

    def forward(self, xyz: Tensor, dirs: Tensor, image_index: Tensor) -> FieldOutput:
        h, logits = self.gate.features_and_logits(xyz)
        probs, index, chosen = top1(logits)
        empty = index == self.gate.empty_index
        keep = torch.ones_like(empty)
        sigma = h.new_zeros(len(h))
        rgb = h.new_zeros(len(h), 3)
        # Scene points, then empty ones, each in their points' order (what two gathers by mask
        # would give), split with one host read instead of two.
        order = torch.argsort(empty.long(), stable=True)
        num_scene = len(empty) - int(empty.sum())
        scene, void = order[:num_scene], order[num_scene:]
        if len(scene):
            # Each expert's output times its gate value, so O is trained by the rendering loss too.
            out = (
                dispatch(self.scene_experts, h[scene], index[scene], keep[scene])
                * chosen[scene, None]
            )
            _, s, c = self.scene_head(
                out, self.dir_encoding(dirs[scene]), self.appearance(image_index[scene])
            )
            sigma, rgb = (
                sigma.index_copy(0, scene, s.to(sigma.dtype)),
                rgb.index_copy(0, scene, c.to(rgb.dtype)),
            )
        if len(void):
            gate = chosen[void, None] if self.empty_gate_grad else chosen[void, None].detach()
            _, s, c = self.empty_head(self.empty_expert(h[void]) * gate)
            sigma, rgb = (
                sigma.index_copy(0, void, s.to(sigma.dtype)),
                rgb.index_copy(0, void, c.to(rgb.dtype)),
            )
        return FieldOutput(sigma, rgb, probs, index, keep)
