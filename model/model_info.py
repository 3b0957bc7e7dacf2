"""The parameter count of every component a method trains, so a user sees what a scene will cost."""

from __future__ import annotations

from model.methods import get_method
from model.methods.base import background, count, switch_nerf  # noqa: F401  (the builders' old home)
from model.profiles import Profile


def model_info(method: str, profile: Profile, num_images: int = 100) -> dict:
    """Per-component parameter counts (appearance embeddings for `num_images` images)."""
    components = get_method(method)(profile).components(num_images)
    return {
        "method": method,
        "profile": profile.name,
        "num_images": num_images,
        "components": components,
        "total": sum(components.values()),
    }


def format_model_info(info: dict) -> str:
    lines = [f"{info['method']} / {info['profile']} ({info['num_images']} appearance embeddings)"]
    width = max(len(k) for k in info["components"])
    lines += [f"  {k:<{width}}  {v:>12,}" for k, v in info["components"].items()]
    lines.append(f"  {'total':<{width}}  {info['total']:>12,}")
    return "\n".join(lines)
