"""LPIPS v0.1 (Zhang et al. 2018) with the VGG and AlexNet backbones, from weights already on this
machine.

The papers we compare against report LPIPS with VGG (Switch-NeRF's released checkpoint scores 0.474
with VGG and 0.397 with AlexNet on one scene), so every number carries its backbone: `lpips_vgg` and
`lpips_alex`.

Each backbone needs two files, never downloaded at run time (docs/TRAINING.md, "LPIPS weights"):

| backbone | ImageNet trunk (torchvision)  | LPIPS linear layers (the `lpips` package) |
|----------|-------------------------------|-------------------------------------------|
| vgg      | `vgg16-397923af.pth`          | `vgg.pth` (`lpips/weights/v0.1/vgg.pth`)   |
| alex     | `alexnet-owt-7be5be79.pth`    | `alex.pth` (`lpips/weights/v0.1/alex.pth`) |

They are looked for in $LECO_LPIPS_DIR, then torch's hub cache (`<hub>/checkpoints`) and an
installed `lpips` package, and each is checked against a pinned sha256 before `torch.load` sees it:
the first file found under a name is the one used, and a file whose hash differs is refused rather
than skipped, so a wrong file in the configured folder is reported instead of silently shadowed.
`load_lpips` never raises: it returns (None, the reason) and evaluations report that backbone's
LPIPS as null with the reason.

The feature stacks are written here with torchvision's layer indices, so torchvision's state_dicts
load as they are and this module needs neither torchvision nor lpips at run time."""

from __future__ import annotations

import hashlib
import importlib.util
import os
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor, nn

# Where each pinned hash comes from (the report and docs/TRAINING.md cite them too):
# - alex.pth, vgg.pth: hashed from `lpips/weights/v0.1/` inside the PyPI wheel
#   lpips-0.1.4-py3-none-any.whl (wheel sha256
#   fd537af5828b69d2e6ffc0a397bd506dbc28ca183543617690844c08e102ec5e).
# - The torchvision trunks: torchvision names each file after the first 8 hex digits of its sha256
#   (what torch.hub's check_hash compares); the full values are the Git LFS/Xet sha256 that Hugging
#   Face shows for byte-identical mirrors (huggingface.co/blanchon/image-gs-models-utils,
#   torch/checkpoints/alexnet-owt-7be5be79.pth, 244,408,911 bytes; huggingface.co/Keiser41/mangaaa,
#   model/vgg16-397923af.pth, 553,433,881 bytes), and they begin with the digits in torchvision's
#   file names.
PINNED_SHA256 = {
    "alexnet-owt-7be5be79.pth": "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02",
    "alex.pth": "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0",
    "vgg16-397923af.pth": "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0",
    "vgg.pth": "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868",
}

# LPIPS v0.1's ScalingLayer: images in [-1, 1] are shifted and scaled to the trunks' ImageNet
# statistics.
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


def alexnet_features() -> nn.Sequential:
    """torchvision's `alexnet().features` up to relu5 (the last tap), same indices: its state_dict
    loads."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2),
        nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1),
        nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1),
        nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1),
        nn.ReLU(),
    )


def vgg16_features() -> nn.Sequential:
    """torchvision's `vgg16().features` up to relu5_3 (index 29; its final max-pool is never
    tapped)."""
    layers: list[nn.Module] = []
    channels = 3
    for block, (width, convs) in enumerate(((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))):
        if block:
            layers.append(nn.MaxPool2d(2, 2))
        for _ in range(convs):
            layers += [nn.Conv2d(channels, width, 3, padding=1), nn.ReLU()]
            channels = width
    return nn.Sequential(*layers)


@dataclass(frozen=True)
class Backbone:
    trunk_file: str  # torchvision's checkpoint, https://download.pytorch.org/models/<trunk_file>
    linear_file: str  # lpips' v0.1 linear layers
    channels: tuple[int, ...]  # of the tapped layers, one linear layer each
    taps: tuple[int, ...]  # indices of the ReLUs LPIPS compares
    features: Callable[[], nn.Sequential]


BACKBONES = {
    "alex": Backbone(
        "alexnet-owt-7be5be79.pth",
        "alex.pth",
        (64, 192, 384, 256, 256),
        (1, 4, 7, 9, 11),
        alexnet_features,
    ),
    # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
    "vgg": Backbone(
        "vgg16-397923af.pth",
        "vgg.pth",
        (64, 128, 256, 512, 512),
        (3, 8, 15, 22, 29),
        vgg16_features,
    ),
}


class LPIPS(nn.Module):
    """Distance between two (H, W, 3) images in [0, 1]; lower is more similar, 0 for identical
    images."""

    shift: Tensor  # buffers registered in __init__, declared so their type is known
    scale: Tensor

    def __init__(self, backbone: str = "alex"):
        super().__init__()
        spec = BACKBONES[backbone]
        self.backbone = backbone
        self.features = spec.features()
        self.taps = spec.taps
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in spec.channels)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False).eval()

    def _taps(self, image: Tensor) -> list[Tensor]:
        # renders may sit on the GPU while this model stays on the CPU
        image = image.to(self.shift.device)
        x = (image.float().permute(2, 0, 1)[None] * 2 - 1 - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:  # unit-normalised over channels, as LPIPS does
                out.append(x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10))
        return out

    @torch.no_grad()
    def forward(self, pred: Tensor, target: Tensor) -> float:
        total = 0.0
        for lin, a, b in zip(self.lins, self._taps(pred), self._taps(target)):
            total += float(lin((a - b) ** 2).mean())
        return total

    def load_weights(self, trunk: dict, linear: dict) -> None:
        # strict: a checkpoint of the other backbone (or a truncated one) fails here instead of
        # scoring garbage.
        self.features.load_state_dict(
            {k.removeprefix("features."): v for k, v in trunk.items() if k.startswith("features.")}
        )
        # lpips stores each linear layer as lin{k}.model.1.weight (a dropout sits at model.0).
        self.lins.load_state_dict(
            {f"{k}.weight": linear[f"lin{k}.model.1.weight"] for k in range(len(self.lins))}
        )


def search_dirs() -> list[Path]:
    """$LECO_LPIPS_DIR, torch's hub checkpoints, an installed lpips package's v0.1 weights: in that
    order."""
    dirs = []
    if os.environ.get("LECO_LPIPS_DIR"):
        dirs.append(Path(os.environ["LECO_LPIPS_DIR"]))
    dirs.append(Path(torch.hub.get_dir()) / "checkpoints")
    spec = importlib.util.find_spec("lpips")
    if spec is not None and spec.origin:
        dirs.append(Path(spec.origin).parent / "weights" / "v0.1")
    return dirs


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        for chunk in iter(lambda: stream.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def hash_problem(path: Path, expected: str | None) -> str | None:
    """None when the file's sha256 is the pinned one, else a sentence naming the file and both
    hashes."""
    if expected is None:  # nothing unpinned is ever loaded
        return f"{path.name} ({path}) has no pinned sha256: refused"
    actual = sha256_of(path)
    if actual == expected:
        return None
    return (
        f"{path.name} ({path}) has sha256 {actual}, expected {expected}: refused, it is not the "
        "published file"
    )


def load_lpips(
    backbone: str = "alex", pins: dict[str, str] | None = None
) -> tuple[LPIPS | None, str]:
    """(model, "") when both of the backbone's files are found locally and match their pinned
    sha256, else (None, the reason). `pins` replaces PINNED_SHA256 (tests pin the hashes of stand-in
    files)."""
    if backbone not in BACKBONES:
        return None, f"unknown LPIPS backbone {backbone!r} (known: {', '.join(BACKBONES)})"
    spec, pins = BACKBONES[backbone], PINNED_SHA256 if pins is None else pins
    dirs = search_dirs()
    found = {
        name: next((d / name for d in dirs if (d / name).is_file()), None)
        for name in (spec.trunk_file, spec.linear_file)
    }
    paths = {name: path for name, path in found.items() if path is not None}
    missing = [name for name in found if name not in paths]
    if missing:
        return None, (
            f"LPIPS ({backbone}) weights not found locally ({', '.join(missing)} in "
            f"{', '.join(str(d) for d in dirs)}); set LECO_LPIPS_DIR to a folder holding them "
            "(docs/TRAINING.md). Nothing is downloaded at run time, so LPIPS is reported as null."
        )
    try:
        problems = [
            p for p in (hash_problem(path, pins.get(name)) for name, path in paths.items()) if p
        ]
    except OSError as error:
        return None, f"LPIPS ({backbone}) weights could not be read: {error}"
    if problems:
        return None, f"LPIPS ({backbone}) is null: " + "; ".join(problems)
    model = LPIPS(backbone)
    try:
        model.load_weights(
            torch.load(paths[spec.trunk_file], map_location="cpu", weights_only=True),
            torch.load(paths[spec.linear_file], map_location="cpu", weights_only=True),
        )
    except (KeyError, RuntimeError, OSError, ValueError, pickle.UnpicklingError) as error:
        return (
            None,
            f"LPIPS ({backbone}) weights in {paths[spec.trunk_file].parent} could not be loaded: "
            f"{error}",
        )
    return model, ""


class LPIPSScores:
    """An evaluation's LPIPS with both backbones: each loaded once, one distance per image, means
    labelled by backbone. A backbone whose weights are absent or refused scores null with its
    reason; the other still scores."""

    ORDER = ("vgg", "alex")  # VGG first: the variant the papers report

    def __init__(self, pins: dict[str, str] | None = None, device: str | torch.device = "cpu"):
        loaded = {name: load_lpips(name, pins) for name in self.ORDER}
        # On the evaluation's device: VGG on a large validation image is slow on a CPU.
        self.models = {
            name: model.to(device) for name, (model, _) in loaded.items() if model is not None
        }
        self.notes = {name: reason or None for name, (_, reason) in loaded.items()}
        self.distances: dict[str, list[float]] = {name: [] for name in self.models}

    def add(self, pred: Tensor, target: Tensor) -> None:
        for name, model in list(self.models.items()):
            try:
                self.distances[name].append(model(pred, target))
            # e.g. an image smaller than the backbone's pooling allows
            except RuntimeError as error:
                del self.models[name]
                self.distances[name] = []
                self.notes[name] = (
                    f"LPIPS ({name}) is null: a {tuple(pred.shape)} image could not be scored: "
                    f"{error}"
                )

    def report(self) -> dict:
        """{"lpips_vgg": mean or None, "lpips_alex": mean or None, "lpips_note": {backbone: reason
        or None}}."""
        out: dict[str, float | dict[str, str | None] | None] = {}
        for name in self.ORDER:
            values = self.distances.get(name) or []
            out[f"lpips_{name}"] = sum(values) / len(values) if values else None
        notes = dict(self.notes)
        for name, values in self.distances.items():
            if not values and notes[name] is None:
                notes[name] = "no image was scored"
        out["lpips_note"] = notes
        return out
