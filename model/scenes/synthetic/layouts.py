"""The layouts a synthetic preset picks (`CityPreset.layout`): each builds the boxes of a scene from
a preset and a seed. Adding one is a file with its builder (boxes on the ground plane, so the truth
stays exact) and a line here."""

from __future__ import annotations

from typing import Callable

from model.scenes.synthetic.city import build_streets
from model.scenes.synthetic.geometry import CityGeometry
from model.scenes.synthetic.presets import CityPreset
from model.scenes.synthetic.village import build_village

Layout = Callable[[CityPreset, int], CityGeometry]

LAYOUTS: dict[str, Layout] = {
    "city": build_streets,  # streets and blocks of buildings, towers, poles and kiosks
    "village": build_village,  # fields, woods, hedgerows and farmsteads
}


def build_city(preset: CityPreset, seed: int) -> CityGeometry:
    """The preset's layout at this seed."""
    if preset.layout not in LAYOUTS:
        raise ValueError(
            f"unknown synthetic layout {preset.layout!r}: choose one of {', '.join(LAYOUTS)}"
        )
    return LAYOUTS[preset.layout](preset, seed)
