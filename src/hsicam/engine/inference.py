"""Reconstruction of whole sensor images, tile by tile.

The network is fully convolutional with a finite receptive field, so a tile computed with a halo
of at least the receptive radius on every side equals the same region of a whole-image pass:
tiles are cut with that halo and only their centres are kept, which makes the mosaic seamless
(exactly, not by blending) while memory stays bounded by the tile size.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import nn

from hsicam.errors import InputError


def receptive_radius(net: nn.Module) -> int:
    """Upper bound of the network's receptive radius (px): Σ over conv layers of dilation·(k−1)/2."""
    r = 0
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            r += m.dilation[0] * (m.kernel_size[0] - 1) // 2
    return r


@torch.no_grad()
def reconstruct_tiled(reconstruct, sensor: torch.Tensor, tile_px: int = 512, halo_px: int = 0,
                      progress: bool = False) -> torch.Tensor:
    """Apply ``reconstruct`` ((1, 1, h, w) → (1, C, h, w)) to a (1, 1, H, W) image in tiles.

    Args:
        tile_px: side of the kept centre of each tile.
        halo_px: context added around each tile (≥ the receptive radius for an exact result).
    """
    if sensor.dim() != 4 or sensor.shape[:2] != (1, 1):
        raise InputError(f"sensor image must be (1, 1, H, W), got {tuple(sensor.shape)}")
    _, _, h, w = sensor.shape
    if h <= tile_px and w <= tile_px:
        return reconstruct(sensor)
    out = None
    ny, nx = math.ceil(h / tile_px), math.ceil(w / tile_px)
    from tqdm.auto import tqdm

    with tqdm(total=ny * nx, disable=not progress, unit="tile") as bar:
        for ty in range(ny):
            for tx in range(nx):
                y0, x0 = ty * tile_px, tx * tile_px
                y1, x1 = min(y0 + tile_px, h), min(x0 + tile_px, w)
                ya, xa = max(y0 - halo_px, 0), max(x0 - halo_px, 0)
                yb, xb = min(y1 + halo_px, h), min(x1 + halo_px, w)
                part = reconstruct(sensor[..., ya:yb, xa:xb])
                if out is None:
                    out = torch.empty(1, part.shape[1], h, w, dtype=part.dtype, device=part.device)
                out[..., y0:y1, x0:x1] = part[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]
                bar.update(1)
    return out


def read_sensor_image(path: str | Path, scale: float | None = None) -> np.ndarray:
    """A sensor image as float32 (H, W) on the simulator's [0, 1] scale.

    ``.npy``: (H, W) or (1, H, W), used as is. 8/16-bit PNG or TIFF: divided by the type's maximum;
    then multiplied by ``scale`` — by default ``sensor_png_scale`` from a ``simulate.json`` beside
    the file (written by ``hsicam simulate``), else 1.
    """
    import json

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such sensor image")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            img = np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{path}: not a readable .npy file ({exc})") from None
        img = img.astype(np.float32)
        if scale is None:
            scale = 1.0
    elif suffix in (".png", ".tif", ".tiff"):
        import imageio.v3 as iio

        try:
            raw = iio.imread(path)
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"{path}: cannot read image ({exc})") from None
        if raw.ndim == 3 and raw.shape[-1] in (3, 4):
            raise InputError(f"{path}: expected a single-channel (monochrome) sensor image, got {raw.shape[-1]} channels")
        if not np.issubdtype(raw.dtype, np.integer):
            img = raw.astype(np.float32)
        else:
            img = raw.astype(np.float32) / float(np.iinfo(raw.dtype).max)
        if scale is None:
            meta = path.parent / "simulate.json"
            scale = float(json.loads(meta.read_text()).get("sensor_png_scale", 1.0)) if meta.is_file() else 1.0
    else:
        raise InputError(f"{path}: unsupported sensor image format (use .npy, .png, .tif)")
    if img.ndim == 3 and img.shape[0] == 1:
        img = img[0]
    if img.ndim != 2:
        raise InputError(f"{path}: sensor image must be 2-D, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise InputError(f"{path}: sensor image contains NaN or Inf")
    return img * np.float32(scale)
