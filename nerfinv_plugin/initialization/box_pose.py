"""A full camera pose from a centred view of the object and the object's box in the observed image.

The view bank holds views rendered with the object's centre on the optical axis at a nominal range. A bank
view that looks like the observed crop gives the attitude; the box gives the rest (as the Augmented
Autoencoder does):

- range: apparent size falls with distance, so ``range = bank range x (bank box / observed box) x
  (observed focal / bank focal)``;
- direction: the observed box centre, moved back by the bank box's offset from where the bank projected
  the object's centre (scaled to the observed size), is where the observed camera sees the centre;
- attitude: the bank view saw the object on its axis; seen off axis, the same appearance belongs to the
  bank camera turned by the rotation that takes the optical axis onto the ray to the object.

All poses are camera-to-world, OpenCV camera axes (x right, y down, z forward) in this module, float64;
callers convert to OpenGL axes at their boundary.
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BankView:
    """What a bank entry knows of its own render: the camera and the object's box in its pixels."""

    w2c_rotation: np.ndarray
    """[3, 3] world-to-camera rotation (OpenCV axes) of the bank camera, in-plane roll included."""
    range: float
    """Distance from the bank camera to the object's centre (model units)."""
    focal: float
    """Focal length of the bank render (pixels, square pixels, principal point at the image centre)."""
    box_offset: tuple[float, float]
    """Box centre minus the principal point (pixels of the bank render): where the box sits relative to
    the projected object centre."""
    box_size: float
    """max(box width, box height), bank pixels."""


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] that takes unit vector ``a`` onto unit vector ``b`` (Rodrigues)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: any half-turn about an axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def pose_from_box(view: BankView, box_centre: tuple[float, float], box_size: float, fx: float, fy: float,
                  cx: float, cy: float, centre: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] (OpenCV axes) of the observed camera, from the matched bank view and the
    observed box (continuous pixel coordinates, nerfstudio's principal point convention); ``centre`` is the
    object's centre in the world (model) frame."""
    if box_size <= 0 or view.box_size <= 0:
        raise ValueError("box sizes must be positive")
    focal = 0.5 * (fx + fy)
    scale = box_size / view.box_size  # observed pixels per bank pixel
    distance = view.range * (focal / view.focal) / scale
    u = box_centre[0] - scale * view.box_offset[0]
    v = box_centre[1] - scale * view.box_offset[1]
    ray = np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
    ray /= np.linalg.norm(ray)
    rotation = rotation_between(np.array([0.0, 0.0, 1.0]), ray) @ view.w2c_rotation
    c2w = np.eye(4)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = np.asarray(centre, dtype=np.float64) - rotation.T @ (distance * ray)
    return c2w
