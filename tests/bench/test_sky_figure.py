"""The sky figure picks the validation view that sees the most sky (infinite ground-truth depth)."""

from types import SimpleNamespace

import pytest
import torch

from bench.sky_figure import sky_view


def test_the_view_with_the_most_sky_is_picked_and_a_scene_without_depth_is_named():
    ground = torch.full((4, 4), 10.0)
    some_sky, most_sky = ground.clone(), ground.clone()
    some_sky[0] = torch.inf
    most_sky[:3] = torch.inf
    views = SimpleNamespace(depth=[ground, most_sky, some_sky])
    assert sky_view(views) == 1
    with pytest.raises(ValueError, match="no ground-truth depth"):
        sky_view(SimpleNamespace(depth=None))
