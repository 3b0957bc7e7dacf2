"""The validation protocol (Mega-NeRF's): a validation view's appearance embedding is never trained
by the run, so scoring it with that embedding colours the view with a random vector. Instead each
validation view's right half is scored, and its embeddings (of every network the phase renders with)
are first set to the mean of the training views' embeddings and then fitted on pixels of its left
half, with the networks frozen. `val_appearance_steps = 0` keeps the mean alone (a fixed policy, for
scenes without per-image appearance)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator

import torch
from torch import nn

from model.methods import Method
from model.methods.base import Networks
from model.scenes.rays import PixelTable, RayBatch
from model.scenes.scene import Views

# left-half pixels per view the embeddings are fitted on (one fixed, seeded set)
FIT_RAYS_PER_VIEW = 256
# Adam on 48-d embeddings initialised N(0, 1): a few dozen steps move them where they belong
FIT_LR = 0.05


def protocol(steps: int) -> str:
    """The sentence every report prints about how validation views were coloured and scored."""
    fit = (
        f"fitted on their left halves ({steps} Adam steps from the mean of the training views' "
        "embeddings, networks frozen)"
        if steps
        else "set to the mean of the training views' embeddings"
    )
    return f"right halves of the validation views scored; their appearance embeddings {fit}"


def left_columns(views: Views, image: int) -> tuple[int, int]:
    return 0, int(views.cameras.width[image]) // 2


def right_columns(views: Views, image: int) -> tuple[int, int]:
    width = int(views.cameras.width[image])
    return width // 2, width


def scored_truth(views: Views, image: int, columns: tuple[int, int] | None) -> torch.Tensor:
    """The ground truth of what is scored, as floats in [0, 1]: the whole image or its columns."""
    truth = views.image(image).float() / 255
    return truth if columns is None else truth[:, columns[0] : columns[1]]


def phase_embeddings(method: Method, models: Networks, phase: str) -> list[nn.Embedding]:
    return [
        m
        for module in method.trained_modules(models, phase)
        for m in module.modules()
        if isinstance(m, nn.Embedding)
    ]


@contextlib.contextmanager
def only_trainable(models: nn.Module, params: list[torch.Tensor]) -> Iterator[None]:
    """Every parameter of `models` frozen but `params`, in eval mode; restored afterwards."""
    previous: dict[torch.Tensor, bool] = {p: p.requires_grad for p in models.parameters()}
    was = models.training
    models.eval()
    for p in previous:
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    try:
        yield
    finally:
        for p, flag in previous.items():
            p.requires_grad_(flag)
        models.train(was)


@dataclass
class FitResult:
    loss_before: float | None
    loss_after: float | None


def fit_rays(views: Views, images: list[int], aabb: torch.Tensor, seed: int = 0) -> RayBatch:
    table, g = PixelTable(views), torch.Generator().manual_seed(seed)
    ids = []
    for image in images:
        left = table.image_pixels(image, left_columns(views, image))
        ids.append(left[torch.randperm(len(left), generator=g)[:FIT_RAYS_PER_VIEW]])
    return table.rays(torch.cat(ids), aabb)


def prepare_validation_appearance(
    method: Method,
    run_models: Networks,
    phase: str,
    views: Views,
    train_views: Views,
    images: list[int],
    aabb: torch.Tensor,
    device: torch.device,
    steps: int,
) -> FitResult:
    """Give `images` of `views` the appearance embeddings the protocol prescribes, in place.
    Training never reads these rows (validation indices come after the training ones), so setting
    them is harmless to it."""
    embeddings = phase_embeddings(method, run_models, phase)
    rows = views.appearance[images].to(device)
    train_rows = train_views.appearance.to(device)
    with torch.no_grad():
        for e in embeddings:
            e.weight[rows] = e.weight[train_rows].mean(dim=0)
    if steps == 0 or not embeddings:
        return FitResult(None, None)
    rays = fit_rays(views, images, aabb).to(device)
    weights = [e.weight for e in embeddings]
    mask = torch.zeros(len(weights[0]), 1, device=device)
    mask[rows] = 1.0
    optimizer = torch.optim.Adam(weights, lr=FIT_LR)
    losses = []
    with only_trainable(run_models, weights), torch.enable_grad():
        for _ in range(steps + 1):
            rendered = method.render(run_models, phase, rays)
            loss = ((rendered.rgb.float() - rays.rgb) ** 2).mean()
            losses.append(float(loss.detach()))
            if len(losses) > steps:
                break  # the last pass only measures the fitted loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            for w in weights:
                # only the validation rows move; Adam leaves zero-gradient rows put
                if w.grad is not None:
                    w.grad.mul_(mask)
            optimizer.step()
    return FitResult(losses[0], losses[-1])
