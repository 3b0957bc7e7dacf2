"""Radiance fields: encodings, experts, heads, the Switch-NeRF main network and LeCO's HMoE."""

from model.fields.encoding import FrequencyEncoding
from model.fields.hmoe import HMoE, OccupancyNetwork
from model.fields.switch_nerf import SwitchNeRF

__all__ = ["FrequencyEncoding", "HMoE", "OccupancyNetwork", "SwitchNeRF"]
