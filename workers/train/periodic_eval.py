"""Validation while training (rank 0), every `eval_every_s` seconds of training time and at the end
of each phase: PSNR / SSIM on the first `eval_views` validation views, and, while an occupancy is
being learned (LeCO's phase 1, the grid all along), its occupancy metrics. This gives the benchmark
its PSNR-against-time curves (the paper's Fig. 9) and F1-against-step curves (Fig. 5). Its time is
not counted as training time."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable

from model.evaluation.metrics import psnr, ssim
from model.evaluation.occupancy import evaluate_occupancy, evaluate_occupancy_exact
from model.scenes.rays import PixelTable
from workers.appearance import prepare_validation_appearance, right_columns, scored_truth
from workers.train.validation import render_image

if TYPE_CHECKING:
    from workers.train.loop import RankRun

OCCUPANCY_RESOLUTION = 64


class PeriodicEval:
    def __init__(self, run: RankRun) -> None:
        self.every = run.cfg.eval_every_s
        views = run.scene.splits.get("val", run.scene.train)
        self.views, self.table = views, PixelTable(views)
        self.count = min(run.cfg.eval_views, len(views))

    def due(self, before_s: float, after_s: float, ending: bool) -> bool:
        """True when this step crossed a multiple of `every` seconds of training time, or ends its
        phase."""
        if self.every is None:
            return False
        return ending or int(after_s // self.every) > int(before_s // self.every)

    def measure(self, run: RankRun, phase: str) -> dict:
        started = time.perf_counter()
        scores = {"val_psnr": 0.0, "val_ssim": 0.0}
        images = list(range(self.count))
        columns: Callable[[int], tuple[int, int] | None] = lambda image: None
        # the protocol; a scene without a val split is scored on training views
        if "val" in run.scene.splits:
            prepare_validation_appearance(
                run.method,
                run.models,
                phase,
                self.views,
                run.scene.train,
                images,
                run.aabb,
                run.device,
                run.cfg.val_appearance_steps,
            )
            columns = lambda image: right_columns(self.views, image)
        for image in images:
            rgb = render_image(
                run.method,
                run.models,
                phase,
                self.table,
                image,
                run.aabb,
                run.device,
                columns(image),
            ).rgb
            truth = scored_truth(self.views, image, columns(image))
            scores["val_psnr"] += psnr(rgb, truth) / self.count
            scores["val_ssim"] += ssim(rgb, truth) / self.count
        occupied = run.method.occupancy(run.models, phase)
        occupancy = None
        if occupied is not None and run.scene.occupancy is not None:
            occupancy = evaluate_occupancy_exact(
                occupied, run.scene.occupancy, self.views, OCCUPANCY_RESOLUTION
            )
        elif occupied is not None and self.views.depth is not None:
            occupancy = evaluate_occupancy(
                occupied, self.views, run.aabb.float(), OCCUPANCY_RESOLUTION
            )
        if occupancy is not None:
            scores.update(
                {f"occupancy_{k}": occupancy[k] for k in ("accuracy", "precision", "recall", "f1")}
            )
        scores["eval_s"] = time.perf_counter() - started
        return scores
