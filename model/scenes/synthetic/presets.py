"""Synthetic city presets: sizes of the district, the flight and the images."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class CityPreset:
    name: str
    blocks: int  # city blocks per side of the square district
    block_size: float  # metres
    street_width: float  # metres
    max_height: float  # metres: the tallest tower
    views: int  # total views (train + val)
    width: int  # pixels
    height: int
    hfov_deg: float
    altitude: float  # metres above the ground
    pitch_deg: float  # below the horizon
    cell_size: float  # ground-truth occupancy cell, metres
    supersample: int = 2  # per-axis samples per pixel
    val_every: int = 10  # every n-th view in capture order is held out

    def as_dict(self) -> dict:
        return asdict(self)


PRESETS = {
    "tiny": CityPreset("tiny", blocks=2, block_size=20.0, street_width=8.0, max_height=24.0, views=12,
                       width=40, height=30, hfov_deg=65.0, altitude=45.0, pitch_deg=50.0, cell_size=0.5,
                       val_every=6),
    "city": CityPreset("city", blocks=4, block_size=28.0, street_width=10.0, max_height=45.0, views=80,
                       width=100, height=75, hfov_deg=65.0, altitude=80.0, pitch_deg=45.0, cell_size=1.0),
    "large": CityPreset("large", blocks=6, block_size=30.0, street_width=10.0, max_height=60.0, views=200,
                        width=200, height=150, hfov_deg=65.0, altitude=100.0, pitch_deg=45.0, cell_size=1.5),
}


def get_preset(preset: str | CityPreset) -> CityPreset:
    if isinstance(preset, CityPreset):
        return preset
    if preset not in PRESETS:
        raise ValueError(f"unknown synthetic preset {preset!r}: choose one of {', '.join(PRESETS)}")
    return PRESETS[preset]
