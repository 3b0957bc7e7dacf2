"""The frozen occupancy network O on its own: the compact artifact a user can take to other
pipelines, saved and loaded without the experts, behind the same estimator interface as the
occupancy grid (model/estimators/base.py); and O as LeCO's guided sampler asks it."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from model.estimators.base import Estimator
from model.fields.hmoe import HMoE, OccupancyNetwork

FORMAT = "leco-occupancy-v1"


class OccupancyPredictor(Estimator):
    """`occupied(points)` for world-frame points, batched so any number of points fits in memory."""

    def __init__(
        self,
        network: OccupancyNetwork,
        chunk: int = 1 << 16,
        empty_threshold: float | None = None,
        frozen: bool = True,
    ):
        """empty_threshold: keep points whose E_e probability is below it instead of the top-1
        decision. frozen=False shares a network that keeps training (guided.online) instead of
        freezing it."""
        self.network = network.eval().requires_grad_(False) if frozen else network
        self.chunk = chunk
        self.empty_threshold = empty_threshold

    @classmethod
    def from_hmoe(cls, model: HMoE, empty_threshold: float | None = None) -> "OccupancyPredictor":
        network = OccupancyNetwork(**model.gate.config)
        network.load_state_dict(model.gate.state_dict())
        return cls(network, empty_threshold=empty_threshold)

    @property
    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.network.parameters())

    @torch.no_grad()
    def occupied(self, points: Tensor) -> Tensor:
        # the estimator interface takes any device
        points = points.to(next(self.network.parameters()).device)
        out = [
            self.network.occupied(points[s : s + self.chunk], self.empty_threshold)
            for s in range(0, len(points), self.chunk)
        ]
        return torch.cat(out) if out else torch.zeros(0, dtype=torch.bool, device=points.device)

    def save(self, path: str | Path) -> None:
        net = self.network
        torch.save({"format": FORMAT, "config": net.config, "state_dict": net.state_dict()}, path)

    @classmethod
    def load(cls, path: str | Path, empty_threshold: float | None = None) -> "OccupancyPredictor":
        data = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise ValueError(f"{path}: not a LeCO occupancy model (expected format {FORMAT!r})")
        network = OccupancyNetwork(**data["config"])
        network.load_state_dict(data["state_dict"])
        return cls(network, empty_threshold=empty_threshold)


class OccupancyQuery(Estimator):
    """O as the guided sampler asks it, one coarse bin point at a time: `occupied` decides, and
    keeps the logits (and the placement head's densities) of the last call, with gradient while
    `learn` is set, for the step's losses. A frozen O (the paper) never learns."""

    def __init__(
        self, network: OccupancyNetwork, empty_threshold: float | None, chunk: int = 1 << 16
    ):
        self.network, self.empty_threshold, self.chunk = network, empty_threshold, chunk
        self.learn = False
        self.logits: Tensor | None = None
        self.sigma: Tensor | None = None

    def occupied(self, points: Tensor) -> Tensor:
        # the sampler calls this under no_grad; cat keeps the graph
        with torch.set_grad_enabled(self.learn):
            starts = range(0, len(points), self.chunk) if len(points) else [0]
            parts = [self.network.query(points[s : s + self.chunk]) for s in starts]
            self.logits = torch.cat([p[0] for p in parts])
            sigmas = [p[1] for p in parts if p[1] is not None]
            self.sigma = torch.cat(sigmas) if sigmas else None
        return self.network.decide(self.logits, self.empty_threshold)

    def density(self, points: Tensor, grad: bool = True) -> Tensor:
        """The placement head's density at points (N, 3), with gradient while `learn` is set (and
        `grad`); the decisions and logits of the last `occupied` call are left as they are."""
        with torch.set_grad_enabled(self.learn and grad):
            sigma = self.network.query(points)[1]
        if sigma is None:
            raise ValueError(
                "guided.placement_fine asks O's placement head: set guided.placement=true"
            )
        return sigma

    def scores(self) -> Tensor:
        """The last call's decision logits, detached: positive exactly where it kept the point."""
        if self.logits is None:
            raise RuntimeError("OccupancyQuery.scores needs an occupied() call first")
        return self.network.decision_logit(self.logits.detach(), self.empty_threshold)
