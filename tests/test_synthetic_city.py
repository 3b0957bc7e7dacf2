"""The synthetic city generator: determinism, exact depth, occupancy, atomic writes, real-looking images."""

import hashlib
import math
import time

import numpy as np
import pytest
import torch

from model.scenes.synthetic import PRESETS, build_city, generate, raycast
from model.scenes.synthetic import writer
from model.scenes.synthetic.raycast import GROUND, SKY
from model.scenes.synthetic.shading import SUN, shade

DRB_TO_ENU = writer.DRB_FROM_ENU.T


def digest(folder):
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("city") / "tiny-0"
    summary = generate("tiny", 0, out)
    return out, summary


def test_same_seed_same_bytes_other_seed_other_city(tiny, tmp_path):
    out, _ = tiny
    again = generate("tiny", 0, tmp_path / "again")
    assert digest(out) == digest(tmp_path / "again")
    other = tmp_path / "other"
    generate("tiny", 1, other)
    a, b = digest(out), digest(other)
    assert a["train/rgbs/000000.png"] != b["train/rgbs/000000.png"]
    assert again["views"] == {"train": 10, "val": 2}


def test_files_in_meganerf_layout(tiny):
    out, summary = tiny
    p = PRESETS["tiny"]
    meta = torch.load(out / "train/metadata/000000.pt", weights_only=True)
    assert (meta["W"], meta["H"]) == (p.width, p.height)
    assert meta["c2w"].shape == (3, 4) and meta["intrinsics"].shape == (4,)
    coords = torch.load(out / "coordinates.pt", weights_only=True)
    assert coords["origin_drb"].shape == (3,) and coords["pose_scale_factor"] > 0
    names = sorted(x.stem for x in (out / "train/rgbs").iterdir()) + sorted(x.stem for x in (out / "val/rgbs").iterdir())
    assert len(names) == len(set(names)) == p.views
    assert np.load(out / "gt/depth/val" / f"{names[-1]}.npy").shape == (p.height, p.width)


def test_stored_depth_equals_ray_casting_the_geometry(tiny):
    """Rebuild rays from the files with the documented conventions and cast them independently."""
    out, _ = tiny
    geometry = build_city(PRESETS["tiny"], 0)
    coords = torch.load(out / "coordinates.pt", weights_only=True)
    checked = 0
    for meta_path in sorted((out / "train/metadata").glob("*.pt"))[:4]:
        meta = torch.load(meta_path, weights_only=True)
        fx, fy, cx, cy = meta["intrinsics"].double().tolist()
        v, u = torch.meshgrid(torch.arange(meta["H"]).double(), torch.arange(meta["W"]).double(), indexing="ij")
        d_cam = torch.stack([(u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -torch.ones_like(u)], -1).reshape(-1, 3)
        c2w = meta["c2w"].double()
        d_drb = d_cam @ c2w[:, :3].T
        d_drb = d_drb / d_drb.norm(dim=-1, keepdim=True)
        centre_drb = coords["origin_drb"] + coords["pose_scale_factor"] * c2w[:, 3]
        dirs, origin = d_drb @ DRB_TO_ENU.T, DRB_TO_ENU @ centre_drb
        t, hit, _ = raycast(geometry, origin.expand_as(dirs), dirs)
        stored = torch.from_numpy(np.load(out / "gt/depth/train" / f"{meta_path.stem}.npy")).double().reshape(-1)
        assert torch.equal(torch.isinf(stored), hit == SKY)
        finite = torch.isfinite(stored)
        assert torch.allclose(stored[finite], t[finite], rtol=1e-4)
        checked += int(finite.sum())
    assert checked > 1000


def brute_force_hit(boxes, o, d):
    """Scalar reference: nearest positive entry over the ground plane and every box."""
    best = -o[2] / d[2] if d[2] < 0 else math.inf
    for lo, hi in boxes.tolist():
        t_near, t_far = -math.inf, math.inf
        for a in range(3):
            if abs(d[a]) < 1e-15:
                if not lo[a] <= o[a] <= hi[a]:
                    t_near, t_far = math.inf, -math.inf
                continue
            t0, t1 = (lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]
            t_near, t_far = max(t_near, min(t0, t1)), min(t_far, max(t0, t1))
        if t_far >= t_near > 0:
            best = min(best, t_near)
    return best


def test_raycast_matches_a_scalar_reference():
    geometry = build_city(PRESETS["tiny"], 5)
    g = torch.Generator().manual_seed(0)
    origins = torch.cat([torch.rand(600, 2, generator=g, dtype=torch.float64) * 70 - 35,
                         torch.rand(600, 1, generator=g, dtype=torch.float64) * 20 + 1], dim=1)
    dirs = torch.randn(600, 3, generator=g, dtype=torch.float64)
    dirs[:300, 2] = -dirs[:300, 2].abs()
    dirs[:5] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # axis-parallel rays
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t, hit, normal = raycast(geometry, origins, dirs)
    ref = torch.tensor([brute_force_hit(geometry.boxes, o.tolist(), d.tolist()) for o, d in zip(origins, dirs)],
                       dtype=torch.float64)
    assert torch.equal(torch.isinf(t), torch.isinf(ref))
    assert torch.allclose(t[torch.isfinite(t)], ref[torch.isfinite(ref)], rtol=1e-9, atol=1e-9)
    assert (hit > 0).sum() > 30 and (hit == GROUND).sum() > 30  # both kinds of surface were exercised
    assert torch.allclose(normal[hit >= 0].norm(dim=-1), torch.ones(int((hit >= 0).sum()), dtype=torch.float64))


def test_occupancy_grid_matches_the_surfaces(tiny):
    """Just inside every surface the grid is occupied; 1.5 cells out along the normal it is free
    (except where another solid is that close, e.g. inside corners)."""
    out, _ = tiny
    geometry = build_city(PRESETS["tiny"], 0)
    arrays = np.load(out / "gt/occupancy.npz")
    occupied, world_from_grid = torch.from_numpy(arrays["occupied"]), torch.from_numpy(arrays["world_from_grid"])
    enu_from_grid = DRB_TO_ENU @ world_from_grid[:3]
    cell = PRESETS["tiny"].cell_size
    g = torch.Generator().manual_seed(2)
    origins = torch.cat([torch.rand(3000, 2, generator=g, dtype=torch.float64) * 60 - 30,
                         torch.full((3000, 1), 60.0, dtype=torch.float64)], 1)
    dirs = torch.randn(3000, 3, generator=g, dtype=torch.float64)
    dirs[:, 2] = -dirs[:, 2].abs() - 0.3
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t, hit, normal = raycast(geometry, origins, dirs)
    p = origins + dirs * t[:, None]
    grid_of = lambda x: torch.linalg.solve(enu_from_grid[:, :3], (x - enu_from_grid[:, 3]).T).T.floor().long()

    def lookup(x):
        ijk = grid_of(x)
        inside = ((ijk >= 0) & (ijk < torch.tensor(occupied.shape))).all(-1)
        ijk = ijk[inside]
        return occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    surface = hit >= 0
    assert lookup(p[surface] - normal[surface] * 0.25 * cell).all()
    outside = lookup(p[surface] + normal[surface] * 1.5 * cell)
    assert len(outside) > 300 and outside.float().mean() < 0.02


def test_occupancy_fraction_low(tiny):
    out, summary = tiny
    print(f"tiny occupied fraction {summary['occupied_fraction']:.4f}")
    assert 0.02 < summary["occupied_fraction"] < 0.3


def test_images_have_texture_sky_and_shadows(tiny):
    out, _ = tiny
    images = [np.asarray(__import__("PIL.Image").Image.open(p)) for p in sorted((out / "train/rgbs").iterdir())]
    assert min(im.std() for im in images) > 10
    depths = [np.load(p) for p in sorted((out / "gt/depth/train").iterdir())]
    assert any(np.isinf(d).any() for d in depths), "the flatter cross pass should see the sky"
    assert all(np.isfinite(d).mean() > 0.5 for d in depths)
    # Shadows: ground points that the sun cannot reach are much darker than sunlit ground.
    geometry = build_city(PRESETS["tiny"], 0)
    g = torch.Generator().manual_seed(1)
    xy = torch.rand(4000, 2, generator=g, dtype=torch.float64) * 60 - 30
    origins = torch.cat([xy, torch.full((4000, 1), 200.0, dtype=torch.float64)], 1)
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(4000, 3)
    colour, t = shade(geometry, origins, down)
    _, hit, _ = raycast(geometry, origins, down)
    ground = hit == GROUND
    p = origins + down * t[:, None]
    shadow_t, _, _ = raycast(geometry, p + torch.tensor([0, 0, 1e-4], dtype=torch.float64), SUN.expand(4000, 3))
    shadowed, lit = ground & torch.isfinite(shadow_t), ground & torch.isinf(shadow_t)
    assert shadowed.sum() > 50 and lit.sum() > 50
    assert colour[shadowed].mean() < 0.6 * colour[lit].mean()


def test_refuses_non_empty_output_and_leaves_it_unchanged(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="exists and is not empty"):
        generate("tiny", 0, out)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    with pytest.raises(ValueError, match="choose one of tiny, city, large"):
        generate("huge", 0, tmp_path / "x")


def test_failure_midway_leaves_nothing(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = writer.save_pt

    def failing(obj, path):
        calls["n"] += 1
        if calls["n"] == 4:
            raise OSError("disk full (simulated)")
        real(obj, path)

    monkeypatch.setattr(writer, "save_pt", failing)
    with pytest.raises(OSError, match="disk full"):
        generate("tiny", 0, tmp_path / "out")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_city_preset_size_time_and_sparsity(tmp_path):
    started = time.perf_counter()
    summary = generate("city", 0, tmp_path / "city")
    seconds = time.perf_counter() - started
    print(f"city: {summary['views']} views {summary['image_size']}, occupied {summary['occupied_fraction']:.4f}, "
          f"{seconds:.1f} s")
    assert 50 <= sum(summary["views"].values()) <= 100 and summary["image_size"] == "100x75"
    assert summary["occupied_fraction"] < 0.2
    assert seconds < 60
