"""Validation while training (rank 0), every `eval_every_s` seconds of training time and at the end
of each phase: PSNR / SSIM on the first `eval_views` validation views, and, while an occupancy is
being learned (LeCO's phase 1, the grid all along), its occupancy metrics. This gives the benchmark
its PSNR-against-time curves (the paper's Fig. 9) and F1-against-step curves (Fig. 5). Its time is
not counted as training time."""

from __future__ import annotations

import time
from typing import Callable

from model.evaluation.metrics import psnr, ssim
from model.evaluation.occupancy import evaluate_occupancy, evaluate_occupancy_exact
from model.scenes.rays import PixelTable
from model.scenes.scene import Scene
from workers.appearance import prepare_validation_appearance, right_columns, scored_truth
from workers.models import LiveNetworks
from workers.train.validation import render_image

OCCUPANCY_RESOLUTION = 64


class PeriodicEval:
    def __init__(self, every_s: float | None, scene: Scene, views: int, appearance_steps: int):
        """`views`: how many validation views each evaluation renders; `appearance_steps`: the
        validation protocol's embedding fit (TrainConfig.val_appearance_steps)."""
        self.every = every_s
        self.scene, self.appearance_steps = scene, appearance_steps
        self.views = scene.splits.get("val", scene.train)
        self.table = PixelTable(self.views)
        self.count = min(views, len(self.views))

    def due(self, before_s: float, after_s: float, ending: bool) -> bool:
        """True when this step crossed a multiple of `every` seconds of training time, or ends its
        phase."""
        if self.every is None:
            return False
        return ending or int(after_s // self.every) > int(before_s // self.every)

    def measure(self, live: LiveNetworks, phase: str) -> dict:
        started = time.perf_counter()
        scores = {"val_psnr": 0.0, "val_ssim": 0.0}
        images = list(range(self.count))
        columns: Callable[[int], tuple[int, int] | None] = lambda image: None
        # the protocol; a scene without a val split is scored on training views
        if "val" in self.scene.splits:
            prepare_validation_appearance(
                live.method,
                live.models,
                phase,
                self.views,
                self.scene.train,
                images,
                live.aabb,
                live.device,
                self.appearance_steps,
            )
            columns = lambda image: right_columns(self.views, image)
        for image in images:
            rgb = render_image(
                live.method,
                live.models,
                phase,
                self.table,
                image,
                live.aabb,
                live.device,
                columns(image),
            ).rgb
            truth = scored_truth(self.views, image, columns(image))
            scores["val_psnr"] += psnr(rgb, truth) / self.count
            scores["val_ssim"] += ssim(rgb, truth) / self.count
        scores.update(self.occupancy(live, phase))
        scores["eval_s"] = time.perf_counter() - started
        return scores

    def occupancy(self, live: LiveNetworks, phase: str) -> dict:
        """The occupancy being learned, scored against the scene's exact cells or its depth maps
        (nothing when neither, or when nothing is learned)."""
        occupied = live.method.occupancy(live.models, phase)
        occupancy = None
        if occupied is not None and self.scene.occupancy is not None:
            occupancy = evaluate_occupancy_exact(
                occupied, self.scene.occupancy, self.views, OCCUPANCY_RESOLUTION
            )
        elif occupied is not None and self.views.depth is not None:
            occupancy = evaluate_occupancy(
                occupied, self.views, live.aabb.float(), OCCUPANCY_RESOLUTION
            )
        if occupancy is None:
            return {}
        return {f"occupancy_{k}": occupancy[k] for k in ("accuracy", "precision", "recall", "f1")}
