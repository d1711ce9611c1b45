"""Rays and cameras.

A `Camera` is a pytree whose geometry (eye, basis, field of view) is traced data, so
moving the camera never retraces a jitted render; only the image size is static.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ._core import Rays, pytree_dataclass

__all__ = ["Rays", "Camera"]


def _unit(v):
    return v / jnp.linalg.norm(v)


@pytree_dataclass
class Camera:
    """A pinhole (perspective) or orthographic camera.

    Pixel (i, j), row 0 at the top, looks along
    ``forward + sx * scale * aspect * right + sy * scale * up`` with
    ``sx = (j + 0.5) / W * 2 - 1`` and ``sy = 1 - (i + 0.5) / H * 2``; `scale` is
    tan(fov / 2) for a perspective camera (fov vertical, degrees) and the half height of
    the view for an orthographic one, whose rays all run along `forward` from the image
    plane through `eye`.
    """

    eye: jax.Array
    forward: jax.Array
    right: jax.Array
    up: jax.Array
    scale: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True))
    height: int = dataclasses.field(metadata=dict(static=True))
    orthographic: bool = dataclasses.field(default=False, metadata=dict(static=True))

    @staticmethod
    def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov: float = 40.0,
                width: int = 256, height: int | None = None) -> Camera:
        """A perspective camera at `eye` looking at `target`; fov is vertical, degrees."""
        if not 0.0 < float(fov) < 180.0:
            raise ValueError(f"fov must be in (0, 180) degrees, got {fov}")
        return _make(eye, target, up, jnp.tan(jnp.deg2rad(jnp.float32(fov)) / 2), width,
                     height, False)

    @staticmethod
    def orthographic_view(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
                          half_height: float = 1.0, width: int = 256,
                          height: int | None = None) -> Camera:
        """An orthographic camera: parallel rays along target - eye, a view
        `2 * half_height` world units tall centred on the eye-target line."""
        if not float(half_height) > 0.0:
            raise ValueError(f"half_height must be positive, got {half_height}")
        return _make(eye, target, up, jnp.float32(half_height), width, height, True)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def rays(self) -> Rays:
        """Primary rays [H, W] with unit directions."""
        h, w = self.height, self.width
        sx = (jnp.arange(w, dtype=jnp.float32) + 0.5) / w * 2.0 - 1.0
        sy = 1.0 - (jnp.arange(h, dtype=jnp.float32) + 0.5) / h * 2.0
        aspect = w / h
        off = (sx[None, :, None] * (self.scale * aspect) * self.right
               + sy[:, None, None] * self.scale * self.up)
        if self.orthographic:
            origin = self.eye + off
            direction = jnp.broadcast_to(self.forward, off.shape)
        else:
            direction = off + self.forward
            direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
            origin = jnp.broadcast_to(self.eye, off.shape)
        return Rays(origin, direction)

    def replace(self, **changes) -> Camera:
        return dataclasses.replace(self, **changes)


def _pixels(name, n) -> int:
    """An image size: a positive whole number (2.7 is an error, not 2)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer, float, np.floating)) \
            or not float(n).is_integer() or n < 1:
        raise ValueError(f"{name} must be a positive whole number of pixels, got {n!r}")
    return int(n)


def _make(eye, target, up, scale, width, height, orthographic) -> Camera:
    width = _pixels("width", width)
    height = width if height is None else _pixels("height", height)
    eye = jnp.asarray(eye, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    up = jnp.asarray(up, jnp.float32)
    if eye.shape != (3,) or target.shape != (3,) or up.shape != (3,):
        raise ValueError("eye, target and up must be 3-vectors")
    _check_basis(eye, target, up)
    forward = _unit(target - eye)
    right = _unit(jnp.cross(forward, up))
    true_up = jnp.cross(right, forward)
    return Camera(eye, forward, right, true_up, jnp.asarray(scale, jnp.float32), width,
                  height, orthographic)


def _check_basis(eye, target, up):
    """Clear errors for a degenerate view when the values are concrete."""
    try:
        e, t, u = (np.asarray(v, np.float64) for v in (eye, target, up))
    except jax.errors.TracerArrayConversionError:
        return
    f = t - e
    if not np.all(np.isfinite([e, t, u])):
        raise ValueError("eye, target and up must be finite")
    if np.linalg.norm(f) == 0.0:
        raise ValueError("eye and target coincide")
    if np.linalg.norm(np.cross(f, u)) <= 1e-6 * np.linalg.norm(f) * np.linalg.norm(u):
        raise ValueError("up is parallel to the view direction; pick another up vector")
