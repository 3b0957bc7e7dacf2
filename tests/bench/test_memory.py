"""`leco bench-memory`: a measured peak RSS beside the API's estimate, for the methods asked."""

import json

from cli.main import main
from model.memory_estimate import FRAME_BYTES_PER_PIXEL


def test_bench_memory_measures_a_peak_and_sets_it_beside_the_estimate(tiny_scene, tmp_path, capsys):
    out = tmp_path / "memory.json"
    words = ["bench-memory", "--scene", str(tiny_scene.root), "--methods", "leco,switch"]
    words += ["--profile", "smoke", "--rays", "64", "--steps", "2", "--out", str(out)]
    assert main(words) == 0
    rows = json.loads(out.read_text())
    assert [(r["method"], r["rays"]) for r in rows] == [("leco", 64), ("switch", 64)]
    for row in rows:
        # a process with torch and a trained run: hundreds of MiB, within the estimate + 25%
        assert 200 < row["peak_rss_mb"] < 1.25 * row["estimate_mb"]
    assert "2 of 2 within the estimate + 25%" in capsys.readouterr().out


def test_bench_memory_frames_measures_what_a_pixel_of_a_frame_costs(tiny_scene, tmp_path, capsys):
    """A render's frame at two sizes, a process each: the peak within the estimate + 25%, and the
    bytes a pixel costs between them within the estimate's count (model/memory_estimate.py). A
    frame holds at least its rays and outputs (80 bytes a pixel); one chunk's activations vary
    by about 45 MiB from process to process, 25 bytes a pixel over the 1.9 million between these
    sizes (55-318 measured over the methods between 160x120, 800x600 and 1600x1200)."""
    out = tmp_path / "frames.json"
    words = ["bench-memory", "--scene", str(tiny_scene.root), "--methods", "switch"]
    words += ["--profile", "smoke", "--frames", "160x120,1600x1200", "--out", str(out)]
    assert main(words) == 0
    small, large = json.loads(out.read_text())
    assert (small["width"], large["width"]) == (160, 1600) and small["bytes_per_pixel"] is None
    for row in (small, large):
        assert 200 < row["peak_rss_mb"] < 1.25 * row["estimate_mb"]
    assert 50 < large["bytes_per_pixel"] < 1.25 * FRAME_BYTES_PER_PIXEL
    assert "2 of 2 within the estimate + 25%" in capsys.readouterr().out


def test_bench_memory_set_reaches_every_run_and_its_estimate(tmp_path, monkeypatch):
    """`--set KEY=VALUE` (as `leco train --set`) in the config each measuring child is given and in
    the estimate beside it; nothing is trained (the children are stood in for)."""
    import pytest

    import bench.memory as memory
    from workers.config import TrainConfig

    children: list[tuple[str, ...]] = []

    def child_peak(*words: str) -> dict:
        children.append(words)
        return {"peak_rss_mb": 300.0, "frame_mb": 10.0}

    monkeypatch.setattr(memory, "child_peak", child_peak)
    monkeypatch.setattr(memory, "scene_shape", lambda scene: (10, 0.5))
    out = tmp_path / "memory.json"
    words = ["bench-memory", "--scene", str(tmp_path), "--methods", "leco", "--profile", "cpu"]
    words += ["--rays", "64,128", "--steps", "2", "--out", str(out)]
    guided = ["--set", "guided.coarse_samples=4096", "--set", "guided.queries_per_bin=16"]
    main(words + guided)
    assert [child[0] for child in children] == ["--one", "--one"]
    configs = [TrainConfig.model_validate_json(child[3]) for child in children]
    for cfg, rays in zip(configs, (64, 128)):
        profile = cfg.resolved_profile()
        assert (profile.guided.coarse_samples, profile.guided.queries_per_bin) == (4096, 16)
        assert profile.rays_per_device == rays  # --rays wins over --set, and so do --steps
        assert cfg == memory.run_config("leco", "cpu", rays, 2, cfg.overrides)
    with_set = json.loads(out.read_text())
    main(words)
    without = json.loads(out.read_text())
    # the estimate counts O's coarse queries: the overrides reach it too
    assert all(a["estimate_mb"] > b["estimate_mb"] for a, b in zip(with_set, without))

    # the child trains the config it is given
    ran: list[TrainConfig] = []
    monkeypatch.setattr(memory, "one_run", lambda scene, run_dir, cfg: ran.append(cfg) or {})
    memory.child_main(list(children[0]))
    assert ran == [configs[0]]

    children.clear()
    main(words + ["--frames", "160x120"] + guided)  # a frame's run too
    [frame] = children
    cfg = TrainConfig.model_validate_json(frame[2])
    assert cfg.resolved_profile().guided.coarse_samples == 4096

    with pytest.raises(SystemExit, match="expected key=value"):
        main(words + ["--set", "guided.coarse_samples"])
