"""LPIPS (Zhang et al. 2018, AlexNet variant v0.1) from weights already on this machine, never downloaded.

Two files are needed: torchvision's AlexNet checkpoint (`alexnet-owt-7be5be79.pth`) and the LPIPS linear
layers (`alex.pth` from the `lpips` package). They are looked for in $LECO_LPIPS_DIR, then in torch's hub
cache (`<hub>/checkpoints`) and the installed `lpips` package. When either is missing, `load_lpips` returns
None with the reason, and evaluations report LPIPS as null.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
from pathlib import Path

import torch
from torch import Tensor, nn

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
LINEAR_FILE = "alex.pth"
CHANNELS = (64, 192, 384, 256, 256)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


class LPIPS(nn.Module):
    """Distance between two (H, W, 3) images in [0, 1]; lower is more similar, 0 for identical images."""

    def __init__(self):
        super().__init__()
        self.features = nn.Sequential(  # torchvision AlexNet's feature layers, same indices
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        )
        self.taps = (1, 4, 7, 9, 11)  # the ReLU outputs LPIPS compares
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in CHANNELS)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False).eval()

    def _taps(self, image: Tensor) -> list[Tensor]:
        x = (image.float().permute(2, 0, 1)[None] * 2 - 1 - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return out

    @torch.no_grad()
    def forward(self, pred: Tensor, target: Tensor) -> float:
        total = 0.0
        for lin, a, b in zip(self.lins, self._taps(pred), self._taps(target)):
            total += float(lin((a - b) ** 2).mean())
        return total

    def load_weights(self, alexnet: dict, linear: dict) -> None:
        self.features.load_state_dict({k.removeprefix("features."): v for k, v in alexnet.items()
                                       if k.startswith("features.")})
        # lpips stores each linear layer as lin{k}.model.1.weight (a dropout sits at model.0).
        self.lins.load_state_dict({f"{k}.weight": linear[f"lin{k}.model.1.weight"] for k in range(len(CHANNELS))})


def _candidates() -> list[Path]:
    dirs = []
    if os.environ.get("LECO_LPIPS_DIR"):
        dirs.append(Path(os.environ["LECO_LPIPS_DIR"]))
    dirs.append(Path(torch.hub.get_dir()) / "checkpoints")
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin:
        dirs.append(Path(spec.origin).parent / "weights" / "v0.1")
    return dirs


def load_lpips() -> tuple[LPIPS | None, str]:
    """(model, "") when both weight files are found locally, else (None, the reason)."""
    found = {}
    for name in (ALEXNET_FILE, LINEAR_FILE):
        found[name] = next((d / name for d in _candidates() if (d / name).is_file()), None)
    missing = [n for n, p in found.items() if p is None]
    if missing:
        where = ", ".join(str(d) for d in _candidates())
        return None, (f"LPIPS weights not found locally ({', '.join(missing)} in {where}); set LECO_LPIPS_DIR to a "
                      "folder holding them. Nothing is downloaded at run time, so LPIPS is reported as null.")
    model = LPIPS()
    try:
        model.load_weights(torch.load(found[ALEXNET_FILE], map_location="cpu", weights_only=True),
                           torch.load(found[LINEAR_FILE], map_location="cpu", weights_only=True))
    except (KeyError, RuntimeError, OSError, pickle.UnpicklingError) as error:
        return None, f"LPIPS weights in {found[ALEXNET_FILE].parent} could not be loaded: {error}"
    return model, ""
