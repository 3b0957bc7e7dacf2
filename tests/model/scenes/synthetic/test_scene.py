"""The synthetic city read back through the Mega-NeRF reader: frames, ground truth and bounds
agree."""

import json

import numpy as np
import pytest
import torch

from cli.main import main
from model.scenes import RaySampler, load_scene, pixel_rays
from model.scenes.bounds import ray_aabb
from model.scenes.synthetic import generate
from model.scenes.synthetic.writer import save_npz


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "tiny-3"
    generate("tiny", 3, out)
    return out


@pytest.fixture(scope="module")
def tiny(tiny_dir):
    return load_scene(tiny_dir)


def surface_samples(views, n_per_view=400, seed=0):
    """World origins, directions and depths of a seeded sample of pixels that see a surface."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for i, depth in enumerate(views.depth):
        h, w = depth.shape
        v = torch.randint(0, h, (n_per_view,), generator=g)
        u = torch.randint(0, w, (n_per_view,), generator=g)
        t = depth[v, u]
        keep = torch.isfinite(t)
        o, d = pixel_rays(views.cameras, torch.full((int(keep.sum()),), i), u[keep], v[keep])
        out.append((o, d, t[keep]))
    return [torch.cat(x) for x in zip(*out)]


def test_reads_as_meganerf_with_ground_truth(tiny):
    assert tiny.format == "meganerf" and tiny.normalization.units == "metres"
    assert tiny.bounds.source == "gt_depth"
    assert tiny.occupancy is not None and tiny.has_depth
    assert len(tiny.train) > 0 and len(tiny.splits["val"]) > 0
    # Drone cameras look down: the forward vectors point below the horizon in the z-up world.
    assert (tiny.train.cameras.forward[:, 2] < -0.3).all()


def test_depth_and_occupancy_agree_in_the_world_frame(tiny):
    """Surface points from the depth maps fall in occupied cells and the air in front of them in
    free cells: this checks the DRB -> z-up conversion of poses, depths and the grid together."""
    occ = tiny.occupancy
    o, d, t = surface_samples(tiny.train)
    cell = float(occ.cell_size.max())
    inside_box = lambda p: ((p >= occ.aabb[0]) & (p <= occ.aabb[1])).all(-1)
    surface = o + d * (t + 0.25 * cell)[:, None]
    in_grid = inside_box(surface)
    assert in_grid.float().mean() > 0.5
    assert occ.lookup(surface[in_grid]).float().mean() > 0.99
    # Where the drone's ray enters the grid (its top, above every roof) is open air; a flipped axis
    # would put the ground layer there.
    entry, _ = ray_aabb(o, d, occ.aabb)
    before = entry + 0.5 * cell < t - cell
    air = o[before] + d[before] * (entry[before] + 0.5 * cell)[:, None]
    assert len(air) > 100
    assert occ.lookup(air).float().mean() < 0.01


def test_bounds_hold_the_observed_surface(tiny):
    o, d, t = surface_samples(tiny.train)
    p = o + d * t[:, None]
    inside = ((p >= tiny.bounds.aabb[0]) & (p <= tiny.bounds.aabb[1])).all(-1)
    assert inside.float().mean() > 0.8  # the rest is ground seen far away: background
    rays = RaySampler(tiny.train, tiny.bounds.aabb, batch_size=256, seed=0).next()
    assert (rays.far >= rays.near).all() and (rays.far > rays.near).float().mean() > 0.5


def test_downscale_keeps_depth_aligned(tiny_dir, tiny):
    half = load_scene(tiny_dir, downscale=2)
    w, h = int(tiny.train.cameras.width[0]), int(tiny.train.cameras.height[0])
    assert half.train.images[0].shape == (h // 2, w // 2, 3)
    assert half.train.depth[0].shape == (h // 2, w // 2)
    assert torch.allclose(
        half.train.cameras.intrinsics[0], tiny.train.cameras.intrinsics[0] / 2, rtol=1e-5
    )


def test_cli_synth_then_info(tmp_path, capsys):
    out = tmp_path / "cli-tiny"
    assert main(["scene", "synth", "--preset", "tiny", "--seed", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["scene", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "meganerf" and info["ground_truth"]["depth"] is True
    assert 0 < info["ground_truth"]["occupancy"]["occupied_fraction"] < 0.5
    assert main(["scene", "synth", "--preset", "tiny", "--seed", "1", "--out", str(out)]) == 2
    assert "leco: error:" in capsys.readouterr().err


def test_city_scale_coordinates_keep_their_precision(tiny_dir, tiny, tmp_path):
    """The same scene placed at UTM-like coordinates (millions of metres) normalises to the same
    world: the origin is subtracted in float64 before anything becomes float32."""
    import shutil

    moved = tmp_path / "utm"
    shutil.copytree(tiny_dir, moved)
    shift = torch.tensor([-120.0, 512_345.25, -4_212_345.75], dtype=torch.float64)
    coords = torch.load(moved / "coordinates.pt", weights_only=True)
    coords["origin_drb"] = coords["origin_drb"] + shift
    torch.save(coords, moved / "coordinates.pt")
    # ground truth is in absolute metres: move it too
    grid = dict(np.load(moved / "gt/occupancy.npz"))
    grid["world_from_grid"][:3, 3] += shift.numpy()
    save_npz(moved / "gt/occupancy.npz", **grid)
    far_away = load_scene(moved)
    assert far_away.normalization.origin.abs().max() > 4e6
    assert torch.allclose(far_away.train.cameras.c2w, tiny.train.cameras.c2w, atol=1e-5)
    assert torch.allclose(far_away.bounds.aabb, tiny.bounds.aabb, atol=1e-5)
    assert torch.equal(far_away.occupancy.occupied, tiny.occupancy.occupied)
    assert torch.allclose(far_away.occupancy.aabb, tiny.occupancy.aabb, atol=1e-5)
