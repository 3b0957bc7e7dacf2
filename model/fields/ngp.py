"""Instant-NGP's radiance field (Müller et al. 2022, section 5.4) in plain PyTorch: a hash encoding
of the point, a density MLP of one hidden layer whose first output is the log-density and whose 15
others are geometry features, and a colour MLP of two hidden layers on those features, the view
direction in spherical harmonics of degree 4, and an appearance embedding (NeRF-W's, as every field
here has). The foreground lives in the scene's box; `NGPBackground` is the same field on
mip-NeRF 360's contracted space, for whatever lies outside it.

The field answers as Switch-NeRF does (a `FieldOutput`), with one "expert", so every sampler that
guides Switch-NeRF (the grid, O, the proposals) guides it unchanged."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.fields.contraction import contracted_unit
from model.fields.hash_encoding import HashEncoding
from model.fields.output import FieldOutput

GEOMETRY_FEATURES = 15  # the density MLP's outputs besides the log-density (Instant-NGP's 16 - 1)
SH_DEGREE = 4  # 16 coefficients


class TruncExp(torch.autograd.Function):
    """exp(x) with the gradient of exp(min(x, 15)): Instant-NGP's density activation, whose gradient
    cannot blow up where a density is already large (torch-ngp's trunc_exp)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: Tensor) -> Tensor:
    return TruncExp.apply(x)


def spherical_harmonics(d: Tensor) -> Tensor:
    """The 16 real spherical harmonics of degree < 4 at unit directions (..., 3) (tiny-cuda-nn's
    SphericalHarmonics encoding, orthonormal on the sphere)."""
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            -0.48860251190291987 * y,
            0.48860251190291987 * z,
            -0.48860251190291987 * x,
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * x * z,
            0.54627421529603959 * (xx - yy),
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * x * y * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ],
        dim=-1,
    )


def mlp(in_dim: int, width: int, hidden_layers: int, out_dim: int) -> nn.Sequential:
    """Instant-NGP's fully fused MLPs: ReLU hidden layers, no biases."""
    dims = [in_dim] + [width] * hidden_layers
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        layers += [nn.Linear(a, b, bias=False), nn.ReLU()]
    return nn.Sequential(*layers, nn.Linear(dims[-1], out_dim, bias=False))


class HashField(nn.Module):
    """Density and colour of points already mapped to [0, 1]^3; the foreground and the background
    differ only in that mapping."""

    def __init__(
        self,
        num_images: int,
        levels: int,
        features: int,
        log2_table_size: int,
        min_resolution: int,
        max_resolution: int,
        width: int,
        appearance_dim: int,
    ):
        super().__init__()
        self.encoding = HashEncoding(
            levels, features, log2_table_size, min_resolution, max_resolution
        )
        self.density_mlp = mlp(self.encoding.out_dim, width, 1, 1 + GEOMETRY_FEATURES)
        self.appearance = nn.Embedding(num_images, appearance_dim)
        colour_in = GEOMETRY_FEATURES + SH_DEGREE**2 + appearance_dim
        self.colour_mlp = mlp(colour_in, width, 2, 3)

    def density(self, unit: Tensor) -> tuple[Tensor, Tensor]:
        """(sigma (N,), geometry features (N, 15)) at points in [0, 1]^3."""
        h = self.density_mlp(self.encoding(unit))
        # Instant-NGP's density is exp of the raw output; in float32 so bf16 cannot overflow it
        return trunc_exp(h[:, 0].float()), h[:, 1:]

    def forward(self, unit: Tensor, dirs: Tensor, image_index: Tensor) -> tuple[Tensor, Tensor]:
        sigma, geometry = self.density(unit)
        colour_in = torch.cat(
            [geometry, spherical_harmonics(dirs), self.appearance(image_index)], dim=-1
        )
        return sigma, torch.sigmoid(self.colour_mlp(colour_in))


class NGPField(nn.Module):
    """The foreground: points of the scene's box, mapped to [0, 1]^3 by it."""

    aabb: Tensor  # a buffer: (2, 3), min and max

    def __init__(self, num_images: int, aabb: Tensor, **hash_field: int):
        super().__init__()
        self.register_buffer("aabb", aabb.detach().float().clone())
        self.hash_field = HashField(num_images, **hash_field)

    @property
    def appearance(self) -> nn.Embedding:
        return self.hash_field.appearance

    def unit(self, xyz: Tensor) -> Tensor:
        return (xyz - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def forward(self, xyz: Tensor, dirs: Tensor, image_index: Tensor) -> FieldOutput:
        sigma, rgb = self.hash_field(self.unit(xyz), dirs, image_index)
        n = len(xyz)
        one = torch.ones(n, 1, device=xyz.device)  # one "expert": the balance loss is constant
        zero = torch.zeros(n, dtype=torch.long, device=xyz.device)
        return FieldOutput(
            sigma, rgb, one, zero, torch.ones(n, dtype=torch.bool, device=xyz.device)
        )


class NGPBackground(nn.Module):
    """The background: world points contracted (mip-NeRF 360) about the box's centre, with the box's
    bounding sphere as the unit sphere, then mapped to [0, 1]^3; the same interface as
    `BackgroundField`."""

    centre: Tensor  # buffers, registered below
    radius: Tensor

    def __init__(
        self, num_images: int, aabb: Tensor, sky_at_infinity: bool = False, **hash_field: int
    ):
        super().__init__()
        self.sky_at_infinity = sky_at_infinity  # read by whoever places its samples
        aabb = aabb.detach().float()
        self.register_buffer("centre", aabb.mean(0))
        self.register_buffer("radius", (aabb[1] - aabb[0]).norm() / 2)
        self.hash_field = HashField(num_images, **hash_field)

    @property
    def appearance(self) -> nn.Embedding:
        return self.hash_field.appearance

    def forward(self, xyz: Tensor, dirs: Tensor, image_index: Tensor) -> tuple[Tensor, Tensor]:
        unit = contracted_unit((xyz - self.centre) / self.radius)
        return self.hash_field(unit, dirs, image_index)
