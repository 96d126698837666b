"""Error maps: where a kernel set's colours differ from the texture it was fitted to.

A PSNR number says how much a fit misses, not where. The error map is a UV-space image laid
out like the bake (``bake.py``), so it can be swapped onto the same GLB in a viewer or
rendered like any texture: per texel the RMS over RGB of kernel colour minus original (both
sRGB in [0, 1]), mapped through a perceptually ordered heat ramp (black, purple, red, orange,
pale yellow) on a fixed scale, so two maps are comparable by eye.
"""

from __future__ import annotations

import numpy as np

#: Absolute sRGB RMS error shown as the top of the ramp (errors above it saturate).
DEFAULT_SCALE = 0.25

# Control points of the heat ramp (position, RGB); close to the "inferno" family, written out
# by hand so the engine needs no plotting library.
_RAMP = np.array(
    [
        (0.00, 0.00, 0.00, 0.02),
        (0.20, 0.20, 0.04, 0.40),
        (0.40, 0.52, 0.11, 0.42),
        (0.60, 0.85, 0.27, 0.23),
        (0.80, 0.98, 0.60, 0.06),
        (1.00, 0.99, 0.99, 0.75),
    ]
)


def heat_colors(values: np.ndarray) -> np.ndarray:
    """``values`` in [0, 1] (any shape) to RGB (..., 3) float32 along the heat ramp."""
    v = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    out = np.stack([np.interp(v, _RAMP[:, 0], _RAMP[:, c]) for c in (1, 2, 3)], axis=-1)
    return out.astype(np.float32)


def resample_texture(texture: np.ndarray, size: int) -> np.ndarray:
    """A square ``size`` x ``size`` copy of an (H, W, 3) float texture in [0, 1].

    Same UV layout (image row 0 is v = 1 in both), so it lines up texel for texel with a
    bake of that resolution; area-averaged when shrinking, bilinear when growing.
    """
    from PIL import Image

    tex = np.asarray(texture, dtype=np.float32)
    if tex.ndim != 3 or tex.shape[2] < 3:
        raise ValueError(f"texture must be (H, W, 3), got {tex.shape}")
    if tex.shape[0] == size and tex.shape[1] == size:
        return np.clip(tex[..., :3], 0.0, 1.0)
    shrinking = tex.shape[0] >= size and tex.shape[1] >= size
    channels = [
        np.asarray(
            Image.fromarray(np.ascontiguousarray(tex[..., c]), mode="F").resize(
                (size, size), Image.Resampling.BOX if shrinking else Image.Resampling.BILINEAR
            )
        )
        for c in range(3)
    ]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def error_texture(
    kernel_texture: np.ndarray,
    original: np.ndarray,
    scale: float = DEFAULT_SCALE,
    covered: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """The heat-map texture of ``kernel_texture`` against ``original`` and the RMS error.

    ``original`` is resampled to the bake's size first. With ``covered`` (the texels a
    triangle covers, (H, W) bool) the RMS is over those texels only and the rest of the map
    is padded from the nearest covered texel, as the bake pads its texture: the padding is
    not surface, and an error there would be invented (the two textures pad differently).
    """
    from hktex_engine.render.bake import pad_texture

    if scale <= 0:
        raise ValueError("scale must be > 0")
    kern = np.asarray(kernel_texture, dtype=np.float32)
    ref = resample_texture(original, kern.shape[0])
    if kern.shape != ref.shape:
        raise ValueError(f"textures differ in shape: {kern.shape} vs {ref.shape}")
    per_texel = np.sqrt(np.mean((kern - ref) ** 2, axis=-1))
    mask = np.ones(per_texel.shape, bool) if covered is None else np.asarray(covered, bool)
    if mask.shape != per_texel.shape or not mask.any():
        raise ValueError("covered must be an (H, W) mask with at least one texel set")
    heat = pad_texture(heat_colors(per_texel / scale), mask)
    return heat, float(np.sqrt(np.mean(per_texel[mask] ** 2)))
