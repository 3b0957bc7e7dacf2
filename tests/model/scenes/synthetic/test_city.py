"""The synthetic scene generator: determinism, exact depth, occupancy, atomic writes, real-looking
images. The ground-truth tests run on a small city and a small village (the two layouts)."""

import hashlib
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from model.scenes.synthetic import PRESETS, build_city, generate, writer
from model.scenes.synthetic.city import POLE
from model.scenes.synthetic.geometry import CANOPY, HEDGE, TRUNK
from model.scenes.synthetic.raycast import GROUND, SKY, raycast
from model.scenes.synthetic.shading import SUN, ground_albedo, shade

DRB_TO_ENU = writer.DRB_FROM_ENU.T  # a rotation: the inverse is the transpose
SPLITS = ("train", "val")


def digest(folder):
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# The village layout at the tiny preset's size: 2 x 2 parcels, 12 views of 40x30.
TINY_VILLAGE = replace(
    PRESETS["village"], name="tiny-village", blocks=2, views=12, width=40, height=30, val_every=6
)


@pytest.fixture(scope="module", params=[PRESETS["tiny"], TINY_VILLAGE], ids=["city", "village"])
def tiny(request, tmp_path_factory):
    preset = request.param
    out = tmp_path_factory.mktemp(preset.layout) / f"{preset.name}-0"
    summary = generate(preset, 0, out)
    print(f"{preset.name}: {summary}")
    return out, summary, preset


def views(out):
    """(split, name) of every view, in capture order."""
    return sorted(
        ((s, p.stem) for s in SPLITS for p in (out / s / "metadata").glob("*.pt")),
        key=lambda v: v[1],
    )


def pixel_rays(out, split, name):
    """World (generator-frame, metres) rays of every pixel centre, rebuilt from the files only, as a
    loader would: pixel -> camera direction -> c2w rotation (DRB) -> generator frame; position
    de-normalised."""
    coords = torch.load(out / "coordinates.pt", weights_only=True)
    meta = torch.load(out / split / "metadata" / f"{name}.pt", weights_only=True)
    fx, fy, cx, cy = meta["intrinsics"].double().tolist()
    v, u = torch.meshgrid(
        torch.arange(meta["H"]).double(), torch.arange(meta["W"]).double(), indexing="ij"
    )
    d_cam = torch.stack(
        [(u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -torch.ones_like(u)], -1
    ).reshape(-1, 3)
    c2w = meta["c2w"].double()
    d_drb = d_cam @ c2w[:, :3].T
    d_drb = d_drb / d_drb.norm(dim=-1, keepdim=True)
    centre_drb = coords["origin_drb"] + coords["pose_scale_factor"] * c2w[:, 3]
    dirs = d_drb @ DRB_TO_ENU.T
    return (DRB_TO_ENU @ centre_drb).expand_as(dirs), dirs


def depth_of(out, split, name):
    return torch.from_numpy(np.load(out / "gt/depth" / split / f"{name}.npy")).double().reshape(-1)


def image_of(out, split, name):
    return np.asarray(Image.open(out / split / "rgbs" / f"{name}.png"))


def test_same_seed_same_bytes_other_seed_other_city(tiny, tmp_path):
    out, _, preset = tiny
    again = generate(preset, 0, tmp_path / "again")
    # PNGs, torch.save files, npy, npz and json alike
    assert digest(out) == digest(tmp_path / "again")
    generate(preset, 1, tmp_path / "other")
    a, b = digest(out), digest(tmp_path / "other")
    pngs = [k for k in a if k.endswith(".png")]
    assert sum(a[k] != b[k] for k in pngs) == len(pngs)
    assert again["views"] == {"train": 10, "val": 2}


def test_files_in_meganerf_layout(tiny):
    out, _, p = tiny
    coords = torch.load(out / "coordinates.pt", weights_only=True)
    assert coords["origin_drb"].dtype == torch.float64 and coords["origin_drb"].shape == (3,)
    assert isinstance(coords["pose_scale_factor"], float) and coords["pose_scale_factor"] > 0
    names = [name for _, name in views(out)]
    # global capture order, unique across splits
    assert names == [f"{i:06d}" for i in range(p.views)]
    val = [int(name) for split, name in views(out) if split == "val"]
    # held out along the path, not a run of neighbours
    assert len(val) == 2 and min(np.diff(val)) > 1
    positions = []
    for split, name in views(out):
        meta = torch.load(out / split / "metadata" / f"{name}.pt", weights_only=True)
        assert (meta["W"], meta["H"]) == (p.width, p.height) and type(meta["W"]) is int
        assert meta["intrinsics"].dtype == meta["c2w"].dtype == torch.float32
        assert meta["c2w"].shape == (3, 4) and meta["intrinsics"][2:].tolist() == [
            p.width / 2,
            p.height / 2,
        ]
        rotation = meta["c2w"][:, :3].double()
        assert torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-6)
        assert torch.linalg.det(rotation) > 0.999
        positions.append(meta["c2w"][:, 3].double())
        image = Image.open(out / split / "rgbs" / f"{name}.png")
        assert image.mode == "RGB" and image.size == (p.width, p.height)
        assert np.load(out / "gt/depth" / split / f"{name}.npy").dtype == np.float32
    positions = torch.stack(positions)  # normalised like Mega-NeRF: centred, max |coordinate| is 1
    assert torch.allclose(positions.mean(0), torch.zeros(3, dtype=torch.float64), atol=1e-6)
    assert abs(float(positions.abs().max()) - 1.0) < 1e-6
    info = json.loads((out / "gt/scene.json").read_text())
    assert info["seed"] == 0 and info["preset"]["name"] == p.name and info["units"] == "metres"
    assert torch.equal(torch.tensor(info["boxes"], dtype=torch.float64), build_city(p, 0).boxes)
    assert info["preset"]["layout"] == p.layout


def test_stored_depth_equals_ray_casting_the_geometry(tiny):
    """Rebuild every pixel ray from the files with the documented conventions and cast it
    independently."""
    out, _, preset = tiny
    geometry = build_city(preset, 0)
    checked = 0
    for split, name in views(out):
        origins, dirs = pixel_rays(out, split, name)
        t, hit, _ = raycast(geometry, origins, dirs)
        stored = depth_of(out, split, name)
        assert torch.equal(torch.isinf(stored), hit == SKY)
        finite = torch.isfinite(stored)
        assert ((stored[finite] - t[finite]).abs() / t[finite]).max() < 1e-4
        checked += int(finite.sum())
    assert checked > 10000


def brute_force_hit(boxes, o, d):
    """Scalar reference: nearest positive entry over the ground plane and every box."""
    best = -o[2] / d[2] if d[2] < 0 else math.inf
    for lo, hi in boxes.tolist():
        t_near, t_far = -math.inf, math.inf
        for a in range(3):
            if d[a] == 0.0:
                if not lo[a] <= o[a] <= hi[a]:
                    t_near, t_far = math.inf, -math.inf
                continue
            t0, t1 = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
            t_near, t_far = max(t_near, min(t0, t1)), min(t_far, max(t0, t1))
        if t_far >= t_near > 0:
            best = min(best, t_near)
    return best


@pytest.mark.parametrize("preset", [PRESETS["tiny"], TINY_VILLAGE], ids=["city", "village"])
def test_raycast_matches_a_scalar_reference(preset):
    geometry = build_city(preset, 5)
    g = torch.Generator().manual_seed(0)
    origins = torch.cat(
        [
            torch.rand(600, 2, generator=g, dtype=torch.float64) * 70 - 35,
            torch.rand(600, 1, generator=g, dtype=torch.float64) * 20 + 1,
        ],
        dim=1,
    )
    dirs = torch.randn(600, 3, generator=g, dtype=torch.float64)
    dirs[:300, 2] = -dirs[:300, 2].abs()
    dirs[:5] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # axis-parallel rays
    # Rays aimed just inside and just outside box corners: a float32 slab test gets these wrong.
    # top corners (max x, y, z)
    corners = geometry.boxes[torch.arange(100) % len(geometry.boxes), 1]
    eye = torch.tensor([-30.0, -40.0, 60.0], dtype=torch.float64)
    nudge = torch.where(torch.arange(100)[:, None] % 2 == 0, -1e-7, 1e-7) * torch.ones(
        3, dtype=torch.float64
    )
    origins[500:] = eye
    dirs[500:] = corners + nudge - eye
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t, hit, normal = raycast(geometry, origins, dirs)
    ref = torch.tensor(
        [brute_force_hit(geometry.boxes, o.tolist(), d.tolist()) for o, d in zip(origins, dirs)],
        dtype=torch.float64,
    )
    assert torch.equal(torch.isinf(t), torch.isinf(ref)) and torch.equal(torch.isinf(t), hit == SKY)
    assert torch.allclose(t[torch.isfinite(t)], ref[torch.isfinite(ref)], rtol=1e-12, atol=1e-12)
    # both kinds of surface were exercised
    assert (hit > 0).sum() > 30 and (hit == GROUND).sum() > 30
    assert torch.allclose(
        normal[hit >= 0].norm(dim=-1), torch.ones(int((hit >= 0).sum()), dtype=torch.float64)
    )
    # t_max: a hit beyond it is no hit.
    t_short, hit_short, _ = raycast(geometry, origins, dirs, t_max=10.0)
    assert torch.equal(torch.where(t <= 10.0, t, torch.inf), t_short)
    assert torch.equal(torch.where(t <= 10.0, hit, SKY), hit_short)


def test_city_has_varied_buildings_and_thin_structures():
    geometry = build_city(PRESETS["city"], 0)
    # seeded, no global RNG
    assert torch.equal(geometry.boxes, build_city(PRESETS["city"], 0).boxes)
    assert not torch.equal(geometry.boxes, build_city(PRESETS["city"], 1).boxes)
    size = geometry.boxes[:, 1] - geometry.boxes[:, 0]
    assert (size > 0).all() and (geometry.boxes[:, 0, 2] >= 0).all()
    buildings = geometry.building[geometry.building > 0]
    parts = torch.bincount(buildings)[1:]
    assert len(parts) >= 20 and parts.max() >= 2  # L-shapes and tiers
    heights = torch.zeros(len(parts), dtype=torch.float64).index_reduce_(
        0, buildings - 1, geometry.boxes[geometry.building > 0, 1, 2], "amax"
    )
    assert heights.max() > 2.5 * heights.median()  # an irregular skyline with towers
    # thin structures
    assert (geometry.kind == POLE).sum() > 10 and size[:, :2].amin(-1).min() <= 0.5


def test_village_is_of_another_character_than_the_city():
    """Wider, lower and sparser than the city, with trees and hedges, flown lower; its flatter pass
    sees the horizon in every view."""
    from model.scenes.synthetic.flight import flight_poses

    city, village = build_city(PRESETS["city"], 0), build_city(PRESETS["village"], 0)
    assert village.extent > 1.3 * city.extent and village.top < 0.5 * city.top
    kinds = torch.bincount(village.kind, minlength=8)
    assert kinds[TRUNK] >= 30 and kinds[CANOPY] == 2 * kinds[TRUNK] and kinds[HEDGE] >= 5

    def built_up(g):  # share of the district's ground under a box
        lo, hi = g.boxes[:, 0, :2], g.boxes[:, 1, :2]
        xy = torch.rand(20000, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
        xy = (xy - 0.5) * g.extent
        return float(((xy[:, None] > lo) & (xy[:, None] < hi)).all(-1).any(-1).double().mean())

    print(f"built-up share: city {built_up(city):.3f}, village {built_up(village):.3f}")
    assert built_up(village) < 0.5 * built_up(city)
    p = PRESETS["village"]
    assert p.altitude < 0.5 * PRESETS["city"].altitude
    poses = flight_poses(p, village.extent, 0)
    # the camera's up vector tilts forward by the pitch: the top image edge is above the horizon
    # when the pitch is below half the vertical field of view
    half_vfov = math.degrees(math.atan(p.height / p.width * math.tan(math.radians(p.hfov_deg / 2))))
    pitch = torch.rad2deg(torch.asin(poses[:, 2, 2])).abs()  # back vector's z = sin(pitch)
    cross = pitch[int(round(p.views * 0.7)) :]
    print(
        f"village pitch: main {pitch[:56].mean():.1f}, cross {cross.mean():.1f}, "
        f"half vfov {half_vfov:.1f}"
    )
    assert (cross < half_vfov).all() and (pitch < half_vfov).float().mean() > 0.4


def cell_lookup(out):
    """(occupied, function: generator-frame points -> (inside grid mask, occupancy of those inside),
    cell size, grid -> generator-frame affine (3, 4))."""
    arrays = np.load(out / "gt/occupancy.npz")
    occupied = torch.from_numpy(arrays["occupied"])
    enu_from_grid = DRB_TO_ENU @ torch.from_numpy(arrays["world_from_grid"])[:3]
    cell = float(enu_from_grid[:, :3].abs().amax(0)[0])

    def lookup(points):
        ijk = (
            torch.linalg.solve(enu_from_grid[:, :3], (points - enu_from_grid[:, 3]).T)
            .T.floor()
            .long()
        )
        inside = ((ijk >= 0) & (ijk < torch.tensor(occupied.shape))).all(-1)
        ijk = ijk[inside]
        return inside, occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]], ijk

    return occupied, lookup, cell, enu_from_grid


def clearance(points, boxes):
    """Euclidean distance from each point to the nearest solid (a box or the ground half-space z <=
    0)."""
    lo, hi = boxes[:, 0], boxes[:, 1]
    gap = torch.maximum(lo[None] - points[:, None], points[:, None] - hi[None]).clamp(min=0)
    return torch.minimum(gap.norm(dim=-1).amin(-1), points[:, 2].clamp(min=0))


def test_occupancy_consistent_with_depth_maps(tiny):
    """Just behind every observed surface the grid is occupied; in front of it, the air is free.
    Checked on the stored depth maps and, for the cells touched, against a brute-force overlap
    test."""
    out, _, preset = tiny
    geometry = build_city(preset, 0)
    occupied, lookup, cell, enu_from_grid = cell_lookup(out)
    diagonal = cell * math.sqrt(3)
    g = torch.Generator().manual_seed(3)
    surface, air = [], []
    for split, name in views(out):
        origins, dirs = pixel_rays(out, split, name)
        depth = depth_of(out, split, name)
        keep = torch.isfinite(depth)
        o, d, t = origins[keep], dirs[keep], depth[keep]
        surface.append(o + d * (t + 1e-3)[:, None])
        for _ in range(4):  # points along the ray well before the surface
            s = torch.rand(len(t), generator=g, dtype=torch.float64) * (t - diagonal).clamp(min=0)
            air.append(o + d * s[:, None])
    surface, air = torch.cat(surface), torch.cat(air)

    inside, occ, _ = lookup(surface)
    assert inside.sum() > 5000 and occ.all()
    inside, occ, ijk = lookup(air)
    print(
        f"air samples in the grid: {int(inside.sum())}, free {occ.logical_not().float().mean():.4f}"
    )
    assert inside.sum() > 5000 and occ.logical_not().float().mean() > 0.97
    # A cell can hold air and solid (a ray passing a wall at a shallow angle): free is guaranteed
    # only with a clearance of a cell diagonal. Those must all be free, and they must be most of the
    # samples.
    clear = clearance(air[inside], geometry.boxes) > diagonal
    assert clear.float().mean() > 0.8 and not occ[clear].any()
    # The exact rule, cell by cell, against every solid for a sample of the cells touched above.
    cells = torch.unique(torch.cat([ijk, lookup(surface)[2]]), dim=0)
    lo = (enu_from_grid[:, :3] @ cells.double().T).T + enu_from_grid[:, 3]
    hi = lo + cell
    overlap = (
        (
            (
                torch.minimum(hi[:, None], geometry.boxes[None, :, 1])
                - torch.maximum(lo[:, None], geometry.boxes[None, :, 0])
            )
            > 1e-9
        )
        .all(-1)
        .any(-1)
    )
    expected = overlap | (lo[:, 2] < -1e-9)  # the ground half-space
    assert torch.equal(occupied[cells[:, 0], cells[:, 1], cells[:, 2]], expected)


def test_occupancy_grid_covers_the_district(tiny):
    out, summary, preset = tiny
    geometry = build_city(preset, 0)
    occupied, lookup, cell, enu_from_grid = cell_lookup(out)
    assert cell == preset.cell_size
    grid_lo = enu_from_grid[:, 3]
    grid_hi = grid_lo + cell * torch.tensor(occupied.shape, dtype=torch.float64)
    assert (grid_lo[:2] < -geometry.extent / 2).all() and (grid_hi[:2] > geometry.extent / 2).all()
    assert grid_lo[2] == -cell and grid_hi[2] > geometry.top
    # ground layer; air above the top
    assert occupied[:, :, 0].all() and not occupied[:, :, -1].any()
    info = json.loads((out / "gt/scene.json").read_text())
    fraction = float(occupied.float().mean())
    assert info["occupied_fraction"] == summary["occupied_fraction"] == round(fraction, 6)
    print(f"{preset.name} occupied fraction {fraction:.4f}")
    assert 0.02 < fraction < 0.3


def test_images_have_texture_sky_and_shadows(tiny):
    out, _, preset = tiny
    geometry = build_city(preset, 0)
    assert min(image_of(out, s, n).std() for s, n in views(out)) > 10
    sky_views, shadowed, lit = 0, [], []
    for split, name in views(out):
        image = torch.from_numpy(image_of(out, split, name).astype(np.float64) / 255).reshape(-1, 3)
        depth = depth_of(out, split, name)
        assert torch.isfinite(depth).float().mean() > 0.5  # drone views look down
        if torch.isinf(depth).any():
            sky_views += 1
            sky = image[torch.isinf(depth)]
            assert (sky[:, 2] > sky[:, 0]).float().mean() > 0.9  # sky blue, not a hole
        # Shadows: divide out the ground's albedo, then compare ground in and out of the sun.
        origins, dirs = pixel_rays(out, split, name)
        t, hit, _ = raycast(geometry, origins, dirs)
        ground = hit == GROUND
        p = origins[ground] + dirs[ground] * t[ground, None]
        blocked, _, _ = raycast(
            geometry, p + torch.tensor([0, 0, 1e-4], dtype=torch.float64), SUN.expand(len(p), 3)
        )
        # sRGB -> linear
        light = (image[ground] ** 2.2 / ground_albedo(p, geometry).double()).mean(-1)
        shadowed.append(light[torch.isfinite(blocked)])
        lit.append(light[torch.isinf(blocked)])
    shadowed, lit = torch.cat(shadowed), torch.cat(lit)
    print(
        f"sky in {sky_views} views; ground light: shadow {shadowed.median():.3f} ({len(shadowed)} "
        f"px), sun {lit.median():.3f} ({len(lit)} px)"
    )
    assert sky_views >= 1, "the flatter cross pass should see the sky"
    assert len(shadowed) > 50 and len(lit) > 50
    assert shadowed.median() < 0.6 * lit.median()


def test_shading_shadow_is_the_only_difference():
    """Same ground point material, light blocked or not: shade() darkens exactly the blocked
    points."""
    geometry = build_city(PRESETS["tiny"], 0)
    g = torch.Generator().manual_seed(1)
    xy = torch.rand(4000, 2, generator=g, dtype=torch.float64) * 60 - 30
    origins = torch.cat([xy, torch.full((4000, 1), 200.0, dtype=torch.float64)], 1)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(4000, 3)
    colour, t = shade(geometry, origins, down)
    _, hit, _ = raycast(geometry, origins, down)
    p = origins + down * t[:, None]
    blocked, _, _ = raycast(
        geometry, p + torch.tensor([0, 0, 1e-4], dtype=torch.float64), SUN.expand(4000, 3)
    )
    ground = hit == GROUND
    light = (colour[ground] / ground_albedo(p[ground], geometry)).double()
    in_shadow = torch.isfinite(blocked[ground])
    assert in_shadow.sum() > 50 and (~in_shadow).sum() > 50
    # Flat ground: one irradiance in the shade, another in the sun (up to the clamp at 1).
    assert torch.allclose(
        light[in_shadow], light[in_shadow][:1].expand_as(light[in_shadow]), rtol=1e-4
    )
    assert light[in_shadow].mean(-1).max() < 0.6 * light[~in_shadow].mean(-1).min()


def test_a_toy_layout_is_a_builder_and_a_line(tmp_path, monkeypatch):
    """A layout registered in LAYOUTS is generated with the same exact truth: one pillar."""
    from model.scenes.synthetic import LAYOUTS
    from model.scenes.synthetic.geometry import BUILDING, CityGeometry

    def pillar(preset, seed):
        box = [[[-3.0, -3.0, 0.0], [3.0, 3.0, 10.0 + seed]]]
        return CityGeometry(
            boxes=torch.tensor(box, dtype=torch.float64),
            kind=torch.tensor([BUILDING]),
            colour=torch.tensor([[0.8, 0.2, 0.2]]),
            building=torch.tensor([1]),
            extent=40.0,
            preset=preset,
        )

    monkeypatch.setitem(LAYOUTS, "pillar", pillar)
    preset = replace(PRESETS["tiny"], name="pillar", layout="pillar")
    out = tmp_path / "pillar-2"
    generate(preset, 2, out)
    info = json.loads((out / "gt/scene.json").read_text())
    assert info["boxes"] == [[[-3.0, -3.0, 0.0], [3.0, 3.0, 12.0]]]
    geometry = build_city(preset, 2)
    hits = 0
    for split, name in views(out):
        origins, dirs = pixel_rays(out, split, name)
        t, hit, _ = raycast(geometry, origins, dirs)
        stored = depth_of(out, split, name)
        finite = torch.isfinite(stored)
        assert ((stored[finite] - t[finite]).abs() / t[finite]).max() < 1e-4
        hits += int((hit == 1).sum())
    assert hits > 100  # the cameras see the pillar
    with pytest.raises(ValueError, match="unknown synthetic layout 'moon'"):
        build_city(replace(preset, layout="moon"), 0)


def test_refuses_non_empty_output_and_leaves_it_unchanged(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="exists and is not empty"):
        generate("tiny", 0, out)
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and (
        out / "keep.txt"
    ).read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]
    with pytest.raises(ValueError, match="choose one of tiny, city, large, village"):
        generate("huge", 0, tmp_path / "x")
    summary = generate("tiny", 0, tmp_path / "empty-is-fine")
    assert summary["path"] == str(tmp_path / "empty-is-fine")


@pytest.mark.parametrize("saver", ["save_png", "save_pt"])
def test_failure_midway_leaves_nothing(tmp_path, monkeypatch, saver):
    calls = {"n": 0}
    real = getattr(writer, saver)

    def failing(obj, path):
        calls["n"] += 1
        if calls["n"] == 4:
            raise OSError("disk full (simulated)")
        real(obj, path)

    monkeypatch.setattr(writer, saver, failing)
    with pytest.raises(OSError, match="disk full"):
        generate("tiny", 0, tmp_path / "out")
    assert calls["n"] == 4 and list(tmp_path.iterdir()) == []  # no OUT, no temporary sibling


@pytest.mark.slow
def test_city_preset_size_and_sparsity(city_scene):
    _, summary, seconds = city_scene
    print(
        f"city: {summary['views']} views {summary['image_size']}, grid {summary['grid_shape']}, "
        f"occupied {summary['occupied_fraction']:.4f}, {seconds:.1f} s"
    )
    views_total = sum(summary["views"].values())
    assert 50 <= views_total <= 100 and summary["image_size"] == "100x75"
    assert 0.05 <= summary["views"]["val"] / views_total <= 0.15
    assert math.prod(summary["grid_shape"]) <= 3_000_000
    # the time is printed, not asserted: speed is a benchmark's job
    assert summary["occupied_fraction"] < 0.2
