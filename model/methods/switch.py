"""S-NeRF* (vanilla Switch-NeRF): stratified coarse + inverse-CDF fine samples through one network.
The reference every speed-up is measured against."""

from __future__ import annotations

from model.methods.base import Method, Networks, SweepPoint
from model.methods.main_phase import MainRender, render_vanilla
from model.render.noise import Noise
from model.scenes.rays import RayBatch


class SwitchNeRFMethod(Method):
    def render_main(
        self,
        models: Networks,
        rays: RayBatch,
        noise: Noise | None,
        phase_step: int | None,
    ) -> MainRender:
        return render_vanilla(models.field, models.background, rays, self.profile, noise)

    def sweep(self) -> list[SweepPoint]:
        v = self.profile.vanilla
        return [
            SweepPoint(
                tag, f"{c} + {f} samples", {"vanilla.coarse_samples": c, "vanilla.fine_samples": f}
            )
            for tag, c, f in (
                ("lean", max(v.coarse_samples // 2, 2), v.fine_samples // 2),
                ("rich", 2 * v.coarse_samples, 2 * v.fine_samples),
            )
        ]
