"""NeRF++-style background for whatever lies beyond the foreground box, shared by every method.

A background point x is described by its direction from the scene centre and its inverse distance,
(x / |x|, 1 / |x|): the inverted sphere, so infinity is a finite input. Samples along a ray are
uniform in inverse depth from the foreground exit to infinity; the last one is made opaque, so the
background always covers whatever the foreground leaves (the sky included).

That last sample lies near 2n times the exit distance (jittered in training), so two cameras that
look the same way see the sky through different points: a far field that does not interpolate
between them (a hash grid) paints each view its own sky. With `sky_at_infinity` the opaque sample
is evaluated at infinity instead (its interval unchanged), where every ray of a direction meets the
same point: the sky becomes a function of the direction alone, shared by every view."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.fields.encoding import FrequencyEncoding
from model.fields.heads import density_activation
from model.render.noise import Noise

MIN_START = 1e-2  # world units: rays that miss the box are background from (almost) the camera on
# world units: "infinity" for the sky's sample (a point there contracts to the unit direction's
# image, 1 / r to 1e-8: no field tells it from a true infinity, and float32 holds it)
SKY_DISTANCE = 1e8


def background_samples(
    far: Tensor, n: int, noise: Noise | None, sky_at_infinity: bool = False
) -> tuple[Tensor, Tensor]:
    """(t_mid, deltas) of n samples per ray from the foreground exit `far` to infinity, (R, n)
    each; `sky_at_infinity`: the opaque last sample at SKY_DISTANCE (see the module docstring)."""
    start = far.clamp(min=MIN_START)
    u = (torch.arange(n, device=far.device, dtype=far.dtype) + 0.5) / n
    if noise is not None:
        u = u + (noise.rand(len(far), n, device=far.device, dtype=far.dtype) - 0.5) / n
    inverse = (1.0 - u) / start[:, None]  # from 1 / start down towards 0
    t = 1.0 / inverse.clamp(min=1e-6)
    deltas = torch.cat([t[:, 1:] - t[:, :-1], torch.full_like(t[:, :1], 1e10)], dim=-1)
    if sky_at_infinity:
        t = torch.cat([t[:, :-1], torch.full_like(t[:, :1], SKY_DISTANCE)], dim=-1)
    return t, deltas


class BackgroundField(nn.Module):
    def __init__(
        self,
        num_images: int,
        width: int = 128,
        layers: int = 4,
        frequencies: int = 10,
        dir_frequencies: int = 4,
        appearance_dim: int = 48,
        density_noise: float = 1.0,
        sky_at_infinity: bool = False,
    ):
        super().__init__()
        self.sky_at_infinity = sky_at_infinity  # read by whoever places its samples
        self.point_encoding = FrequencyEncoding(frequencies, in_dim=4)
        self.dir_encoding = FrequencyEncoding(dir_frequencies)
        self.appearance = nn.Embedding(num_images, appearance_dim)
        dims = [self.point_encoding.out_dim] + [width] * layers
        self.trunk = nn.Sequential(
            *[m for a, b in zip(dims[:-1], dims[1:]) for m in (nn.Linear(a, b), nn.ReLU())]
        )
        self.sigma = nn.Linear(width, 1)
        self.colour = nn.Sequential(
            nn.Linear(width + self.dir_encoding.out_dim + appearance_dim, width // 2),
            nn.ReLU(),
            nn.Linear(width // 2, 3),
        )
        self.density_noise = density_noise

    def forward(self, xyz: Tensor, dirs: Tensor, image_index: Tensor) -> tuple[Tensor, Tensor]:
        r = xyz.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        h = self.trunk(self.point_encoding(torch.cat([xyz / r, 1.0 / r], dim=-1)))
        sigma = density_activation(self.sigma(h).squeeze(-1), self.density_noise, self.training)
        rgb = torch.sigmoid(
            self.colour(torch.cat([h, self.dir_encoding(dirs), self.appearance(image_index)], -1))
        )
        return sigma, rgb
