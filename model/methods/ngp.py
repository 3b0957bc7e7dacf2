"""The hash-grid family (the paper's Appendix C): Instant-NGP's field (model/fields/ngp.py) for the
box and on the contracted space for the background, in place of Switch-NeRF and Mega-NeRF's
background, under each sampler the Switch-NeRF methods have: `ngp` marches the occupancy grid (the
paper's NGP), `ngp-leco` follows LeCO's occupancy network (the paper's NGP+Ours), `ngp-prop`
the proposal networks and `ngp-leco-prop` the proposals inside O's keep. A row and its Switch-NeRF
namesake differ only in the main networks, and the rows of a family only in the sampler."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from model.fields.ngp import NGPBackground, NGPField
from model.methods.base import Networks, background, count
from model.methods.grid import GridMethod
from model.methods.leco.method import LeCOMethod
from model.methods.leco_prop import LeCOPropMethod
from model.methods.prop import ProposalMethod
from model.profiles import Profile


def hash_fields(profile: Profile) -> tuple[dict, dict]:
    """The keyword arguments of the foreground's and the background's HashField."""
    g, a = profile.ngp, profile.network.appearance_dim
    shared = dict(features=g.features, min_resolution=g.min_resolution, width=g.width)
    fore = dict(
        levels=g.levels,
        log2_table_size=g.log2_table_size,
        max_resolution=g.max_resolution,
        appearance_dim=a,
        **shared,
    )
    back = dict(
        levels=g.background_levels,
        log2_table_size=g.background_log2_table_size,
        max_resolution=max(g.background_max_resolution, g.min_resolution),
        appearance_dim=a,
        **shared,
    )
    return fore, back


def ngp_networks(profile: Profile, num_images: int, aabb: Tensor) -> tuple[NGPField, nn.Module]:
    fore, back = hash_fields(profile)
    if profile.ngp.background == "mlp":  # the Switch-NeRF methods' far field
        return NGPField(num_images, aabb, **fore), background(profile, num_images)
    sky = profile.background.sky_at_infinity
    return NGPField(num_images, aabb, **fore), NGPBackground(num_images, aabb, sky, **back)


class HashGridNetworks:
    """Mixed in before a sampler's Method: the hash-grid networks, their learning rate and their
    parameter counts."""

    profile: Profile
    field_is_phase1s = False  # LeCO's phase 1 trains no hash grid: the main phase starts fresh

    def main_networks(self, num_images: int, aabb: Tensor) -> tuple[nn.Module, nn.Module]:
        return ngp_networks(self.profile, num_images, aabb)

    def main_components(self, num_images: int) -> dict[str, int]:
        with torch.device("meta"):
            field, behind = ngp_networks(self.profile, num_images, torch.zeros(2, 3))
        return {
            "main.hash_tables": count(field.hash_field.encoding),
            "main.mlps": count(field.hash_field.density_mlp, field.hash_field.colour_mlp),
            "main.appearance": count(field.appearance),
            "background": count(behind),
        }

    def phase_lr(self, phase: str) -> tuple[float, float | None]:
        if phase == "main":  # hash tables want Instant-NGP's rate, far above an MLP's
            return self.profile.ngp.lr, self.profile.ngp.lr_final
        return super().phase_lr(phase)  # type: ignore[misc]

    def adam_options(self, phase: str) -> dict:
        if phase == "main":
            g = self.profile.ngp
            return {"betas": (0.9, g.adam_beta2), "eps": g.adam_eps}
        return super().adam_options(phase)  # type: ignore[misc]

    def distortion_weight(self) -> float:
        return self.profile.ngp.distortion_weight

    def lr_scales(self, models: Networks, phase: str) -> list[tuple[nn.Module, float]]:
        if phase == "main" and self.profile.ngp.background == "mlp":
            # an MLP far field trains at the MLPs' rate, not the hash tables'
            return [(models.background, self.profile.lr / self.profile.ngp.lr)]
        return super().lr_scales(models, phase)  # type: ignore[misc]


class NGPMethod(HashGridNetworks, GridMethod):
    grid_section = "ngp.grid"  # Instant-NGP's own grid, cascades reaching into the background


class NGPLeCOMethod(HashGridNetworks, LeCOMethod):
    pass


class NGPProposalMethod(HashGridNetworks, ProposalMethod):
    pass


class NGPLeCOPropMethod(HashGridNetworks, LeCOPropMethod):
    pass
