"""Editor roster of the paper (appendix "Benchmark Model Details"): price per 1k images.

Keys are lower-case model ids as commonly sent to the APIs; ``price_per_image`` also
matches case-insensitively on the display name. Local models have no price (None).
"""

from __future__ import annotations

ROSTER: dict[str, tuple[str, float | None]] = {
    "gpt-image-2": ("GPT-Image-2", 211.0),
    "gpt-image-1.5": ("GPT-Image-1.5", 133.0),
    "nano-banana": ("Nano-Banana", 39.0),
    "nano-banana-2": ("Nano-Banana 2", 67.0),
    "flux-kontext-max": ("FLUX-Kontext-Max", 80.0),
    "flux-2-pro": ("FLUX-2-Pro", 45.0),
    "seedream-4.5": ("Seedream-4.5", 40.0),
    "qwen-image-edit-2511": ("Qwen-Image-Edit-2511", None),
    "firered-image-edit-1.1": ("FireRed-Image-Edit-1.1", None),
    "omnigen2": ("OmniGen2", None),
    "hunyuan-image-3.0": ("Hunyuan-Image-3.0", None),
}


def price_per_image(model: str) -> float | None:
    """USD per image, or None when unknown (cost is then not accounted)."""
    key = model.strip().lower()
    for k, (name, per_1k) in ROSTER.items():
        if key in (k, name.lower(), name.lower().replace(" ", "-")):
            return None if per_1k is None else per_1k / 1000.0
    return None
