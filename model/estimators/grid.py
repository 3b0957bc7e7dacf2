"""The "S+Grid" baseline: nerfacc's OccGridEstimator semantics re-implemented in plain PyTorch
(nerfacc's sampling needs CUDA). One level over the foreground box by default; with `levels` > 1,
Instant-NGP's cascades: level l covers the box scaled by 2^l about its centre, and a point belongs
to the finest level that holds it. Every cost it has (update queries, the culling pass) is explicit
so benchmarks can charge it to the grid.

Update (every `every` steps): during warm-up every cell is queried; afterwards a random quarter of
all cells plus up to a quarter as many occupied cells, each at a jittered point inside the cell;
occupancy keeps max(decay * old, density * step_size); a cell is occupied when its value exceeds
min(mean, threshold)."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from model.estimators.base import Estimator
from model.render.samples import PackedSamples


class GridEstimator(Estimator):
    """nerfacc's OccGridEstimator in plain PyTorch: a binary grid over the foreground box, kept
    from the density it was last asked (the module's docstring says how)."""

    def __init__(self, aabb: Tensor, resolution: int = 128, levels: int = 1):
        self.aabb = aabb.float()
        # read once here: the march's step size needs it every step, and a read there waits
        self.diagonal = float((self.aabb[1] - self.aabb[0]).norm())
        self.resolution = resolution
        self.levels = levels
        self.values = torch.zeros(levels * resolution**3)
        # everything may be occupied until updated
        self.binary = torch.ones(levels * resolution**3, dtype=torch.bool)
        self.queries = 0  # density evaluations spent on updates, for honest cost accounting

    def to(self, device: torch.device | str) -> "GridEstimator":
        """Moves the grid to the main network's device (its random draws stay on the CPU
        generator)."""
        self.aabb, self.values, self.binary = (
            self.aabb.to(device),
            self.values.to(device),
            self.binary.to(device),
        )
        return self

    @property
    def num_cells(self) -> int:
        return self.levels * self.resolution**3

    def level_box(self, level: Tensor | int) -> tuple[Tensor, Tensor]:
        """The corners of a cascade level (level 0 is the box itself, exactly)."""
        if isinstance(level, int) and level == 0:
            return self.aabb[0], self.aabb[1]
        centre, half = self.aabb.mean(0), (self.aabb[1] - self.aabb[0]) / 2
        scale = 2.0 ** torch.as_tensor(level, device=self.aabb.device, dtype=torch.float32)
        scale = scale[..., None] if scale.dim() else scale
        return centre - half * scale, centre + half * scale

    def _cell_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Each point's cell (level-major) and whether any level holds it."""
        r = self.resolution
        unit = (points - self.aabb[0]) / (self.aabb[1] - self.aabb[0])
        ijk = torch.floor(unit * r).long()
        inside = ((ijk >= 0) & (ijk < r)).all(-1)
        level = torch.zeros(len(points), dtype=torch.long, device=points.device)
        if self.levels > 1:
            # Every point goes through the outer levels' rule and keeps it where level 0 did not
            # hold it: elementwise, so the same values as for the outer points alone, without a
            # mask to gather by (each gather waits on CUDA).
            outer = ~inside
            centre, half = self.aabb.mean(0), (self.aabb[1] - self.aabb[0]) / 2
            reach = ((points - centre) / half).abs().amax(-1)
            # the finest level 2^l >= reach; at least 1, as level 0 did not hold the point
            outer_level = torch.ceil(torch.log2(reach.clamp(min=1.0))).long().clamp(min=1)
            lo, hi = self.level_box(outer_level)
            outer_ijk = torch.floor((points - lo) / (hi - lo) * r).long()
            held = ((outer_ijk >= 0) & (outer_ijk < r)).all(-1) & (outer_level < self.levels)
            level = torch.where(outer, outer_level, level)
            ijk = torch.where(outer[:, None], outer_ijk, ijk)
            inside = torch.where(outer, held, inside)
        ijk = ijk.clamp(0, r - 1)
        level = level.clamp(max=self.levels - 1)
        return ((level * r + ijk[:, 0]) * r + ijk[:, 1]) * r + ijk[:, 2], inside

    def occupied(self, points: Tensor) -> Tensor:
        """Points no level holds are free."""
        index, inside = self._cell_index(points.to(self.aabb.device))
        return self.binary[index] & inside

    def beyond(self, points: Tensor) -> Tensor:
        """Points outside the outermost level: the grid knows nothing of them."""
        return ~self._cell_index(points.to(self.aabb.device))[1]

    def not_free(self, points: Tensor) -> Tensor:
        """occupied | beyond, from one cell lookup: what a cascaded render must keep."""
        index, inside = self._cell_index(points.to(self.aabb.device))
        return self.binary[index] | ~inside

    @torch.no_grad()
    def update(
        self,
        step: int,
        density_fn: Callable[[Tensor], Tensor],
        step_size: float,
        threshold: float = 0.01,
        decay: float = 0.95,
        warmup_steps: int = 256,
        every: int = 16,
        generator: torch.Generator | None = None,
    ) -> bool:
        """Returns True when this step updated the grid."""
        if step % every:
            return False
        n, device = self.num_cells, self.values.device
        if step < warmup_steps:
            cells = torch.arange(n)
        else:
            uniform = torch.randint(0, n, (n // 4,), generator=generator)
            occupied = torch.nonzero(self.binary).squeeze(1).cpu()
            if len(occupied) > n // 4:
                occupied = occupied[torch.randint(0, len(occupied), (n // 4,), generator=generator)]
            cells = torch.cat([uniform, occupied])
        r = self.resolution
        ijk = torch.stack([(cells // (r * r)) % r, (cells // r) % r, cells % r], -1).float()
        jitter = torch.rand(len(cells), 3, generator=generator)
        cells, unit = cells.to(device), ((ijk + jitter) / r).to(device)
        lo, hi = self.level_box(0) if self.levels == 1 else self.level_box(cells // r**3)
        points = lo + unit * (hi - lo)
        value = torch.cat(
            [
                density_fn(points[s : s + 65536]).float().reshape(-1)
                for s in range(0, len(points), 65536)
            ]
        )
        self.queries += len(points)
        # Duplicate cells in one update: the largest value wins, as with nerfacc's scatter of
        # maxima.
        fresh = torch.zeros(n, device=device).scatter_reduce_(
            0, cells, value * step_size, reduce="amax", include_self=False
        )
        touched = torch.zeros(n, dtype=torch.bool, device=device)
        touched[cells] = True
        self.values = torch.where(touched, torch.maximum(self.values * decay, fresh), self.values)
        self.binary = self.values > min(float(self.values.mean()), threshold)
        return True


def cull_by_transmittance(
    samples: PackedSamples,
    sigma: Tensor,
    num_rays: int,
    early_stop_eps: float = 1e-4,
    alpha_threshold: float = 0.0,
) -> PackedSamples:
    """nerfacc's optional no-gradient pass: drop samples behind an opaque point (transmittance below
    early_stop_eps) or nearly transparent ones (alpha below alpha_threshold). `sigma` comes from an
    extra no-grad query of the main network: that query is part of the grid method's cost."""
    from model.render.volume import packed_weights

    with torch.no_grad():
        weights, _ = packed_weights(sigma, samples.deltas, samples.ray_index, num_rays)
        alpha = -torch.expm1(-(sigma * samples.deltas).clamp(min=0))
        transmittance = torch.where(
            alpha > 0, weights / alpha.clamp(min=1e-12), torch.ones_like(alpha)
        )
        keep = (transmittance >= early_stop_eps) & (alpha >= alpha_threshold)
    return PackedSamples(samples.starts[keep], samples.ends[keep], samples.ray_index[keep])
