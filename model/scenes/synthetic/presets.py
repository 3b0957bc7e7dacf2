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
    # A scale scene reuses each render for several views: a render `render_margin` times the image
    # size, cut into `crops_per_render` images at seeded offsets. A crop is an exact image of the
    # same camera with its principal point shifted, so the scene stays consistent while rendering
    # costs a fraction.
    crops_per_render: int = 1
    render_margin: float = 1.0
    depth_maps: bool = True  # gt/depth per view (float32 at image size: 1.2 MB a 640x480 view)
    layout: str = "city"  # city: streets and blocks; village: fields, woods and farmsteads
    # the flatter pass (30% of the views) flies at this share of pitch_deg: it sees the horizon
    cross_pitch_share: float = 0.5

    def as_dict(self) -> dict:
        return asdict(self)

    def split_of(self, view: int) -> str:
        """The split of the view at this position in capture order (every val_every-th is held
        out, from the middle of the first run)."""
        return "val" if view % self.val_every == self.val_every // 2 else "train"

    def split_info(self) -> dict:
        """Each split's images and their sizes, as scene info (model/scenes/info.py) records them
        once the scene is generated: what the API checks a job against while it generates."""
        counts = {"train": 0, "val": 0}
        for view in range(self.views):
            counts[self.split_of(view)] += 1
        size = f"{self.width}x{self.height}"
        return {
            "downscale": 1,
            "cameras": self.views,
            "splits": {
                name: {"images": n, "image_sizes": [size], "images_by_size": {size: n}}
                for name, n in counts.items()
                if n
            },
        }


PRESETS = {
    "tiny": CityPreset(
        "tiny",
        blocks=2,
        block_size=20.0,
        street_width=8.0,
        max_height=24.0,
        views=12,
        width=40,
        height=30,
        hfov_deg=65.0,
        altitude=45.0,
        pitch_deg=50.0,
        cell_size=0.5,
        val_every=6,
    ),
    "city": CityPreset(
        "city",
        blocks=4,
        block_size=28.0,
        street_width=10.0,
        max_height=45.0,
        views=80,
        width=100,
        height=75,
        hfov_deg=65.0,
        altitude=80.0,
        pitch_deg=45.0,
        cell_size=1.0,
    ),
    "large": CityPreset(
        "large",
        blocks=6,
        block_size=30.0,
        street_width=10.0,
        max_height=60.0,
        views=200,
        width=200,
        height=150,
        hfov_deg=65.0,
        altitude=100.0,
        pitch_deg=45.0,
        cell_size=1.5,
    ),
    # Countryside of another character than the city, for judging settings on a scene they were
    # not chosen on: wider (228 m), sparser and lower (trees and barns, a few silos), flown at 30 m;
    # the flatter pass (and some of the main one) sees the horizon and the sky.
    "village": CityPreset(
        "village",
        blocks=5,
        block_size=36.0,
        street_width=8.0,
        max_height=18.0,
        views=80,
        width=100,
        height=75,
        hfov_deg=70.0,
        altitude=30.0,
        pitch_deg=28.0,
        cell_size=1.0,
        layout="village",
        cross_pitch_share=0.4,
    ),
    # Mega-NeRF's captures at the scale of the paper's 1/4-resolution training (2,000+ photos):
    # 2,000 views of 640x480 (614M pixels, a 1.8 GB pixel cache), from 125 renders; no depth maps
    # (3.7 GB more).
    "xl": CityPreset(
        "xl",
        blocks=8,
        block_size=30.0,
        street_width=10.0,
        max_height=60.0,
        views=2000,
        width=640,
        height=480,
        hfov_deg=65.0,
        altitude=110.0,
        pitch_deg=45.0,
        cell_size=2.0,
        supersample=1,
        val_every=100,
        crops_per_render=16,
        render_margin=1.2,
        depth_maps=False,
    ),
}


def get_preset(preset: str | CityPreset) -> CityPreset:
    if isinstance(preset, CityPreset):
        return preset
    if preset not in PRESETS:
        raise ValueError(f"unknown synthetic preset {preset!r}: choose one of {', '.join(PRESETS)}")
    return PRESETS[preset]
