"""S+Ours (LeCO): phase 1 learns the scene's occupancy with the HMoE (section 3.3); the main phase
trains Switch-NeRF on the samples its frozen gating network O keeps (section 3.4). The cpu profile's
settings that are not in the paper (warm start, O learning online, the sampler's options) are chosen
here from the profile."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor, nn

from model.estimators.occupancy import OccupancyPredictor, OccupancyQuery
from model.estimators.online import OnlineOccupancy
from model.estimators.proposal import anneal_power
from model.fields.hmoe import HMoE
from model.methods.base import (
    Method,
    Networks,
    Occupied,
    Step,
    SweepPoint,
    background,
    count,
    mean_of,
)
from model.methods.leco.guided_render import phase1_placement_loss, render_guided
from model.methods.leco.phase1 import occupancy_step, render_hmoe
from model.methods.leco.warm_start import warm_start_main
from model.methods.main_phase import MainRender
from model.profiles import Profile
from model.render.noise import Noise
from model.render.volume import Rendered
from model.scenes.rays import RayBatch


def hmoe(profile: Profile, num_images: int) -> HMoE:
    n, o = profile.network, profile.occupancy
    return HMoE(
        num_images,
        width=n.width,
        num_scene_experts=n.num_experts,
        expert_layers=n.expert_layers,
        xyz_frequencies=n.xyz_frequencies,
        dir_frequencies=n.dir_frequencies,
        appearance_dim=n.appearance_dim,
        homogeneous=o.homogeneous,
        density_noise=n.density_noise,
        empty_gate_grad=o.empty_gate_grad,
        gate_width=o.gate_width,
        gate_relu_every_layer=o.gate_relu_every_layer,
        empty_expert_layers=o.empty_expert_layers,
        placement_head=profile.guided.placement,
    )


class LeCOMethod(Method):
    aabb: Tensor  # the scene's box, made by build(): where online_box_points are drawn

    def __init__(self, profile: Profile):
        super().__init__(profile)
        self.predictor: OccupancyPredictor | None = None
        self.query: OccupancyQuery | None = None  # O as the main phase's sampler asks it

    # ----- static
    # -------------------------------------------------------------------------------------
    def build(self, num_images: int, aabb: Tensor) -> Networks:
        self.aabb = aabb.detach().float()
        models = Networks()
        models.hmoe = hmoe(self.profile, num_images)
        models.occupancy_background = background(self.profile, num_images)
        models.field, models.background = self.main_networks(num_images, aabb)
        return models

    def components(self, num_images: int) -> dict[str, int]:
        with torch.device("meta"):
            occ = hmoe(self.profile, num_images)
        return {
            "occupancy_network": count(occ.gate),
            "phase1.scene_experts": count(occ.scene_experts),
            "phase1.scene_head": count(occ.scene_head),
            "phase1.empty_expert_and_head": count(occ.empty_expert, occ.empty_head),
            "phase1.appearance": count(occ.appearance),
            **super().components(num_images),
        }

    def sweep(self) -> list[SweepPoint]:
        g = self.profile.guided
        cull = SweepPoint("cull", "culling T < 1e-3", {"guided.cull_transmittance": 1e-3})
        if g.placement:  # O places a fixed budget per hit ray: the budget is what to sweep
            return [
                SweepPoint(tag, f"{n} main samples", {"guided.main_samples": n})
                for tag, n in (("lean", max(g.main_samples // 2, 1)), ("rich", 2 * g.main_samples))
            ] + [cull]
        lean = (
            SweepPoint("lean", f"dilation {g.dilate - 1}", {"guided.dilate": g.dilate - 1})
            if g.dilate > 0
            else SweepPoint(
                "lean", f"split {max(g.split // 2, 1)}", {"guided.split": max(g.split // 2, 1)}
            )
        )
        return [
            lean,
            SweepPoint(
                "rich",
                f"{2 * g.coarse_samples} coarse bins",
                {"guided.coarse_samples": 2 * g.coarse_samples},
            ),
            cull,
        ]

    # ----- a run
    # --------------------------------------------------------------------------------------
    def phase_lr(self, phase: str) -> tuple[float, float | None]:
        # Phase 1 at the occupancy lr, constant as in the paper unless occupancy.lr_final is set.
        if phase == "occupancy":
            return self.profile.occupancy.lr, self.profile.occupancy.lr_final
        return super().phase_lr(phase)

    def trained_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        if phase == "occupancy":
            return [models.hmoe, models.occupancy_background]
        return super().trained_modules(models, phase)

    def warm_starts(self) -> bool:
        """Whether the main phase starts from phase 1's experts, heads and embeddings
        (`guided.warm_start`); a main field phase 1 did not train (a hash grid) starts fresh."""
        return self.profile.guided.warm_start and self.field_is_phase1s

    field_is_phase1s = True  # the main field is Switch-NeRF, whose experts the HMoE's resemble

    def o_learns(self) -> bool:
        """Whether O keeps learning in the main phase: its keep/drop decisions (online) or its
        placement."""
        return self.profile.guided.online or self.profile.guided.placement

    def compiled_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        if phase == "occupancy":
            # Measured: compiled, the HMoE's phase 1 took 2.8x as long (ngp-leco on city-0, 1,500
            # steps: about 265 s against 95), its expert dispatch a host read between graphs
            return []
        return super().compiled_modules(models, phase)

    def extra_parameters(self, models: Networks, phase: str) -> list[nn.Parameter]:
        if phase == "main" and self.o_learns():
            # model/estimators/online.py, model/estimators/placement.py
            return list(models.hmoe.gate.parameters())
        return []

    def start_phase(
        self,
        models: Networks,
        phase: str,
        fresh: bool,
        device: torch.device,
        log: Callable[[str], None],
    ) -> None:
        if phase != "main":
            return
        g = self.profile.guided
        if fresh and self.warm_starts():
            behind = models.occupancy_background if g.warm_start_background else None
            copied = warm_start_main(
                models.field, models.background, models.hmoe, behind, g.warm_start_density
            )
            log(f"main phase warm-started from phase 1: {', '.join(copied)}")
        models.hmoe.requires_grad_(False)
        if self.o_learns():  # O keeps learning, so the predictor shares the live network
            gate = models.hmoe.gate.requires_grad_(True)
            self.query = OnlineOccupancy(
                gate,
                g.empty_threshold,
                g.online_surface,
                free_opacity=g.online_free_opacity,
                free_error=g.online_free_error,
                surface_points=g.online_surface_points,
                dense_points=g.online_dense_points,
                box=self.aabb.to(device),
                box_points=g.online_box_points,
                box_alpha=g.online_box_alpha,
            )
            self.predictor = OccupancyPredictor(
                gate, empty_threshold=g.empty_threshold, frozen=False
            )
        else:
            # frozen O (section 3.4)
            self.predictor = OccupancyPredictor.from_hmoe(models.hmoe, g.empty_threshold)
            self.predictor.network.to(device)
            self.query = OccupancyQuery(self.predictor.network, g.empty_threshold)

    def lr_ramp_steps(self, phase: str) -> int:
        g = self.profile.guided
        return g.warm_start_ramp if phase == "main" and self.warm_starts() else 0

    def step(self, models: Networks, step: Step) -> tuple[Tensor, dict]:
        rays, noise = step.rays, step.noise
        if step.phase == "occupancy":
            g = self.profile.guided
            extra = None
            # O's placement head learns the HMoE's own weights
            if g.placement and g.placement_in_phase1:
                extra = (
                    "placement_loss",
                    partial(phase1_placement_loss, models.hmoe.gate, rays, g, noise),
                )
            return occupancy_step(
                models.hmoe,
                models.occupancy_background,
                rays,
                self.profile.occupancy,
                self.profile.background.samples,
                noise,
                step.progress,
                extra,
            )
        return super().step(models, step)

    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        g = self.profile.guided
        query = self.main_query()
        # O's keep/drop loss starts once the main network has had `online_warmup` steps to fit what
        # its weights will teach; its placement learns from the first step (every
        # `placement_every`-th), its histogram annealed in from uniform. On a step where neither
        # learns, O is asked without gradient.
        keeps = phase_step is not None and g.online_learns(phase_step)
        places = phase_step is not None and g.placement_learns(phase_step)
        query.learn = keeps or places
        learner = query if keeps and isinstance(query, OnlineOccupancy) else None
        anneal = anneal_power(phase_step, g.placement_anneal_steps, 10.0)
        return render_guided(
            models.field,
            models.background,
            rays,
            self.profile,
            query,
            noise,
            learner,
            places,
            anneal,
        )

    def main_query(self) -> OccupancyQuery:
        if self.query is None:
            raise RuntimeError(
                "LeCO's main phase renders with O's predictor: start_phase('main') makes it"
            )
        return self.query

    def render(self, models: Networks, phase: str, rays: RayBatch) -> Rendered:
        if phase == "occupancy":
            return render_hmoe(
                models.hmoe,
                models.occupancy_background,
                rays,
                self.profile.occupancy.samples_per_ray,
                self.profile.background.samples,
                None,
            )[0]
        return super().render(models, phase, rays)

    def occupancy(self, models: Networks, phase: str) -> Occupied | None:
        if phase != "occupancy" and not self.o_learns():
            # O is frozen in the main phase: its metrics are those at the end of phase 1
            return None
        # A frozen copy of O as it is now, deciding as the main phase will (the final evaluation
        # does the same).
        predictor = OccupancyPredictor.from_hmoe(models.hmoe, self.profile.guided.empty_threshold)
        predictor.network.to(next(models.hmoe.parameters()).device)
        return predictor.occupied

    def final_occupancy(self, models: Networks) -> Occupied | None:
        return self.predictor.occupied if self.predictor is not None else None

    def decision_rules(self, models: Networks) -> dict[str, Occupied]:
        if self.predictor is None or self.predictor.empty_threshold is None:
            return {}
        top1 = OccupancyPredictor(self.predictor.network, empty_threshold=None, frozen=False)
        return {"top1": top1.occupied}  # the paper's rule: O's top-1 gate is a scene expert

    def point_cloud_samples(self) -> int:
        return self.profile.guided.coarse_samples

    def save_final(self, final: Path) -> None:
        if self.predictor is not None:
            self.predictor.save(final / "occupancy.pt")

    def load_final(self, models: Networks, final: Path, device: torch.device) -> None:
        if (final / "occupancy.pt").is_file():
            self.predictor = OccupancyPredictor.load(
                final / "occupancy.pt", self.profile.guided.empty_threshold
            )
            self.predictor.network.to(device)
            self.query = OccupancyQuery(self.predictor.network, self.profile.guided.empty_threshold)

    def summary_occupancy(self, final: Path, main: list[dict], first: list[dict]) -> dict:
        saved = torch.load(final / "occupancy.pt", weights_only=True)["state_dict"]
        last = first[-1] if first else {}
        return {
            "params": sum(p.numel() for p in saved.values()),
            "empty_fraction": last.get("fraction_empty"),
            "density_ratio": last.get("density_ratio"),
            "occupancy_ratio": mean_of(main, "occupancy_ratio"),
        }
