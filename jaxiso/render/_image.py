"""Images: a float [H, W, 3] numpy array that shows itself inline in Jupyter."""

from __future__ import annotations

import io
import os

import numpy as np

__all__ = ["Image", "save_png", "to_uint8"]


def to_uint8(img) -> np.ndarray:
    """[H, W, 3] floats in [0, 1] -> uint8 (NaN -> 0, clipped)."""
    a = np.nan_to_num(np.asarray(img, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


class Image(np.ndarray):
    """A rendered image: a float32 numpy array [H, W, 3] with values in [0, 1] that
    Jupyter displays as a PNG. `save(path)` writes a PNG."""

    def __new__(cls, array):
        return np.asarray(array, np.float32).view(cls)

    def _repr_png_(self):
        if self.ndim != 3 or self.shape[-1] not in (1, 3, 4):
            return None
        from PIL import Image as PILImage
        buf = io.BytesIO()
        PILImage.fromarray(to_uint8(self)).save(buf, format="PNG")
        return buf.getvalue()

    def save(self, path) -> str:
        return save_png(self, path)


def save_png(img, path) -> str:
    """Write a float [H, W, 3] (or [H, W]) image in [0, 1] as a PNG; returns the path."""
    from PIL import Image as PILImage
    a = np.asarray(img)
    if a.ndim not in (2, 3):
        raise ValueError(f"save_png needs an [H, W] or [H, W, C] image, got shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"the image has {int(bad.sum())} NaN or inf values (of {a.size}); "
                         "a PNG of them would be a wrong picture")
    path = os.fspath(path)
    parent = os.path.dirname(path)
    if parent:
        os.makedirs(parent, exist_ok=True)
    PILImage.fromarray(to_uint8(a)).save(path, format="PNG")
    return path
