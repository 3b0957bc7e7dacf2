"""S+Ours (LeCO): phase 1 learns the scene's occupancy with the HMoE (section 3.3); the main phase trains
Switch-NeRF on the samples its frozen gating network O keeps (section 3.4). The cpu profile's settings that are
not in the paper (warm start, O learning online, the sampler's options) are chosen here from the profile."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from torch import Tensor, nn

from model.fields.hmoe import HMoE
from model.main_phase import MainRender, render_guided
from model.methods.base import (
    Method,
    Networks,
    Occupied,
    PhaseMemory,
    SweepPoint,
    background,
    count,
    mean_of,
    switch_nerf,
)
from model.occupancy import OccupancyPredictor
from model.occupancy_phase import occupancy_step, render_hmoe
from model.online_occupancy import OnlineOccupancy
from model.profiles import Profile
from model.rendering import Rendered
from model.scenes.rays import RayBatch
from model.warm_start import warm_start_main


def hmoe(profile: Profile, num_images: int) -> HMoE:
    n = profile.network
    return HMoE(num_images, n.width, n.num_experts, n.expert_layers, n.xyz_frequencies, n.dir_frequencies,
                n.appearance_dim, profile.occupancy.homogeneous, n.density_noise,
                profile.occupancy.empty_gate_grad, profile.occupancy.gate_width,
                profile.occupancy.gate_relu_every_layer, profile.occupancy.empty_expert_layers)


class LeCOMethod(Method):
    name = "leco"
    label = "S+Ours (LeCO)"
    colour = "#d62728"
    role = "ours"
    phases = ("occupancy", "main")
    budget_share = {"occupancy": 0.25}  # with a wall-clock budget, phase 1 stops at this share of it
    has_occupancy = True

    def __init__(self, profile: Profile):
        super().__init__(profile)
        self.predictor: OccupancyPredictor | None = None
        self.online: OnlineOccupancy | None = None

    # ----- static -------------------------------------------------------------------------------------
    def build(self, num_images: int, aabb: Tensor) -> Networks:
        models = Networks()
        models.hmoe = hmoe(self.profile, num_images)
        models.occupancy_background = background(self.profile, num_images)
        models.field = switch_nerf(self.profile, num_images)
        models.background = background(self.profile, num_images)
        return models

    def components(self, num_images: int) -> dict[str, int]:
        with torch.device("meta"):
            occ = hmoe(self.profile, num_images)
        return {"occupancy_network": count(occ.gate), "phase1.scene_experts": count(occ.scene_experts),
                "phase1.scene_head": count(occ.scene_head),
                "phase1.empty_expert_and_head": count(occ.empty_expert, occ.empty_head),
                "phase1.appearance": count(occ.appearance), **super().components(num_images)}

    def main_samples_bound(self) -> int:
        g = self.profile.guided
        return g.coarse_samples * g.split

    def memory(self, num_images: int) -> dict[str, PhaseMemory]:
        with torch.device("meta"):
            occ, behind = hmoe(self.profile, num_images), count(background(self.profile, num_images))
        main = super().memory(num_images)["main"]
        gate = count(occ.gate)
        samples = self.profile.occupancy.samples_per_ray
        return {"occupancy": PhaseMemory(trained=count(occ) + behind, samples_per_ray=samples),
                "main": PhaseMemory(trained=main.trained, frozen=gate, samples_per_ray=main.samples_per_ray,
                                    render_samples_per_ray=max(main.samples_per_ray, samples))}

    def sweep(self) -> list[SweepPoint]:
        g = self.profile.guided
        lean = (SweepPoint("lean", f"dilation {g.dilate - 1}", {"guided.dilate": g.dilate - 1}) if g.dilate > 0
                else SweepPoint("lean", f"split {max(g.split // 2, 1)}", {"guided.split": max(g.split // 2, 1)}))
        return [lean,
                SweepPoint("rich", f"{2 * g.coarse_samples} coarse bins",
                           {"guided.coarse_samples": 2 * g.coarse_samples}),
                SweepPoint("cull", "culling T < 1e-3", {"guided.cull_transmittance": 1e-3})]

    # ----- a run --------------------------------------------------------------------------------------
    def phase_steps(self, phase: str) -> int:
        return self.profile.occupancy.steps if phase == "occupancy" else self.profile.main_steps

    def phase_lr(self, phase: str) -> tuple[float, float | None]:
        # Phase 1 at the occupancy lr, constant as in the paper unless occupancy.lr_final is set.
        if phase == "occupancy":
            return self.profile.occupancy.lr, self.profile.occupancy.lr_final
        return super().phase_lr(phase)

    def trained_modules(self, models: Networks, phase: str) -> list[nn.Module]:
        if phase == "occupancy":
            return [models.hmoe, models.occupancy_background]
        return super().trained_modules(models, phase)

    def extra_parameters(self, models: Networks, phase: str) -> list[nn.Parameter]:
        if phase == "main" and self.profile.guided.online:
            return list(models.hmoe.gate.parameters())  # O keeps learning (model/online_occupancy.py)
        return []

    def start_phase(self, models: Networks, phase: str, fresh: bool, device: torch.device,
                    log: Callable[[str], None]) -> None:
        if phase != "main":
            return
        g = self.profile.guided
        if fresh and g.warm_start:
            copied = warm_start_main(models.field, models.background, models.hmoe, models.occupancy_background)
            log(f"main phase warm-started from phase 1: {', '.join(copied)}")
        models.hmoe.requires_grad_(False)
        if g.online:  # O keeps learning, so the predictor shares the live network
            gate = models.hmoe.gate.requires_grad_(True)
            self.online = OnlineOccupancy(gate, g.empty_threshold, g.online_surface)
            self.predictor = OccupancyPredictor(gate, empty_threshold=g.empty_threshold, frozen=False)
        else:
            self.predictor = OccupancyPredictor.from_hmoe(models.hmoe, g.empty_threshold)  # frozen O (section 3.4)
            self.predictor.network.to(device)

    def lr_ramp_steps(self, phase: str) -> int:
        g = self.profile.guided
        return g.warm_start_ramp if phase == "main" and g.warm_start else 0

    def step(self, models: Networks, phase: str, rays: RayBatch, generator: torch.Generator | None,
             progress: float, phase_step: int, seed: int) -> tuple[Tensor, dict]:
        if phase == "occupancy":
            return occupancy_step(models.hmoe, models.occupancy_background, rays, self.profile.occupancy,
                                  self.profile.background.samples, generator, progress)
        return super().step(models, phase, rays, generator, progress, phase_step, seed)

    def render_main(self, models: Networks, rays: RayBatch, generator: torch.Generator | None,
                    phase_step: int | None) -> MainRender:
        # O learns once the main network has had `online_warmup` steps to fit what its weights will teach.
        learns = phase_step is not None and self.profile.guided.online_learns(phase_step)
        online = self.online if learns else None
        occupied = online.occupied if online else self.frozen_predictor().occupied
        return render_guided(models.field, models.background, rays, self.profile, occupied, generator, online)

    def frozen_predictor(self) -> OccupancyPredictor:
        if self.predictor is None:
            raise RuntimeError("LeCO's main phase renders with O's predictor: start_phase('main') makes it")
        return self.predictor

    def render(self, models: Networks, phase: str, rays: RayBatch) -> Rendered:
        if phase == "occupancy":
            return render_hmoe(models.hmoe, models.occupancy_background, rays, self.profile.occupancy.samples_per_ray,
                               self.profile.background.samples, None)[0]
        return super().render(models, phase, rays)

    def occupancy(self, models: Networks, phase: str) -> Occupied | None:
        if phase != "occupancy":
            return None  # O is frozen in the main phase: its metrics are those at the end of phase 1
        # A frozen copy of O as it is now, deciding as the main phase will (the final evaluation does the same).
        predictor = OccupancyPredictor.from_hmoe(models.hmoe, self.profile.guided.empty_threshold)
        predictor.network.to(next(models.hmoe.parameters()).device)
        return predictor.occupied

    def final_occupancy(self, models: Networks) -> Occupied | None:
        return self.predictor.occupied if self.predictor is not None else None

    def point_cloud_samples(self) -> int:
        return self.profile.guided.coarse_samples

    def save_final(self, final: Path) -> None:
        if self.predictor is not None:
            self.predictor.save(final / "occupancy.pt")

    def load_final(self, models: Networks, final: Path, device: torch.device) -> None:
        if (final / "occupancy.pt").is_file():
            self.predictor = OccupancyPredictor.load(final / "occupancy.pt", self.profile.guided.empty_threshold)
            self.predictor.network.to(device)

    def summary_occupancy(self, final: Path, main: list[dict], first: list[dict]) -> dict:
        saved = torch.load(final / "occupancy.pt", weights_only=True)["state_dict"]
        last = first[-1] if first else {}
        return {"params": sum(p.numel() for p in saved.values()), "empty_fraction": last.get("fraction_empty"),
                "density_ratio": last.get("density_ratio"), "occupancy_ratio": mean_of(main, "occupancy_ratio")}
