"""The torch-free parameter counts (model/sizes.py) that the API's memory check uses equal the
networks' own, built on PyTorch's meta device, for every profile and every setting that changes a
network's shape."""

import pytest
import torch

from model import sizes
from model.fields.proposal import ProposalDensity
from model.methods.base import background, count, switch_nerf
from model.methods.costs import proposal_width
from model.methods.leco.method import hmoe
from model.methods.ngp import ngp_networks
from workers.config import TrainConfig

SHAPES = [
    {},
    {"guided.placement": False, "guided.placement_fine": 0, "guided.placement_in_phase1": False},
    {"occupancy.gate_width": 24, "occupancy.homogeneous": True},
    {"occupancy.empty_expert_layers": 3},
    {
        "network.width": 40,
        "network.num_experts": 3,
        "network.expert_layers": 2,
        "network.appearance_dim": 5,
        "ngp.levels": 3,
        "ngp.features": 4,
        "ngp.log2_table_size": 9,
        "ngp.width": 24,
        "ngp.background_levels": 1,
        "network.xyz_frequencies": 4,
        "network.dir_frequencies": 2,
        "background.width": 18,
        "background.layers": 2,
    },
    {"ngp.background": "mlp", "background.width": 20},
]


@pytest.mark.parametrize("profile", ["smoke", "cpu", "paper"])
@pytest.mark.parametrize("overrides", SHAPES)
def test_sizes_count_what_the_networks_hold(profile, overrides):
    p = TrainConfig(method="leco", profile=profile, overrides=overrides).resolved_profile()
    with torch.device("meta"):
        occupancy = hmoe(p, 7)
        field, behind = ngp_networks(p, 7, torch.zeros(2, 3))
        built = {
            "ngp_field": count(field),
            "ngp_background": count(behind),
            "switch_nerf": count(switch_nerf(p, 7)),
            "background": count(background(p, 7)),
            "hmoe": count(occupancy),
            "occupancy_network": count(occupancy.gate),
            "proposal": count(
                ProposalDensity(proposal_width(p), p.prop.layers, p.network.xyz_frequencies)
            ),
        }
    assert {
        "ngp_field": sizes.ngp_field(p, 7),
        "ngp_background": sizes.ngp_background(p, 7),
        "switch_nerf": sizes.switch_nerf(p, 7),
        "background": sizes.background(p, 7),
        "hmoe": sizes.hmoe(p, 7),
        "occupancy_network": sizes.occupancy_network(p),
        "proposal": sizes.proposal(proposal_width(p), p.prop.layers, p.network.xyz_frequencies),
    } == built
