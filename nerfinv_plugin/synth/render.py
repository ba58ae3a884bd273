"""Rendering a scene through a pinhole camera given in OpenCV terms, and applying lens distortion."""

from dataclasses import dataclass

import cv2
import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

# Mitsuba cameras look along +z with +y up and +x to the left; OpenCV's x points right and y down.
_OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics in OpenCV's convention: pixel centres at integer coordinates, so the centre of a W-wide
    image is at x = (W - 1) / 2. Mitsuba renders square pixels, hence a single focal length."""

    width: int
    height: int
    focal: float
    """Focal length in pixels (fx = fy)."""
    cx: float
    cy: float

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.focal, 0, self.cx], [0, self.focal, self.cy], [0, 0, 1.0]])

    @property
    def fov_x_deg(self) -> float:
        return float(np.degrees(2 * np.arctan(0.5 * self.width / self.focal)))

    def padded(self, pad_x: int, pad_y: int) -> "PinholeCamera":
        """The same camera on a canvas grown by ``pad`` pixels on every side."""
        return PinholeCamera(self.width + 2 * pad_x, self.height + 2 * pad_y, self.focal,
                             self.cx + pad_x, self.cy + pad_y)


def _sensor(c2w_cv: np.ndarray, camera: PinholeCamera, spp: int) -> mi.Sensor:
    to_world = mi.ScalarTransform4f((np.asarray(c2w_cv, float) @ _OPENCV_TO_MITSUBA).tolist())
    # Mitsuba puts the optical axis at the film centre (W/2 in continuous coordinates, where pixel i spans
    # [i, i+1]); OpenCV's cx = c means continuous c + 0.5. The offset is a fraction of the film size, and
    # Mitsuba's x runs right-to-left in the image, y bottom-to-top.
    offset_x = (camera.cx + 0.5 - camera.width / 2) / camera.width
    offset_y = (camera.cy + 0.5 - camera.height / 2) / camera.height
    return mi.load_dict({
        "type": "perspective",
        "fov_axis": "x",
        "fov": camera.fov_x_deg,
        "principal_point_offset_x": -offset_x,
        "principal_point_offset_y": -offset_y,
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": to_world,
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height, "pixel_format": "rgba",
                 "rfilter": {"type": "box"}},
    })


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def render_view(scene: mi.Scene, c2w_cv: np.ndarray, camera: PinholeCamera, spp: int,
                seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Render one view. Returns the sRGB ``uint8`` image over the black background [H, W, 3] and the
    object's coverage in [0, 1] [H, W] (alpha: 0 on the background)."""
    image = np.array(mi.render(scene, sensor=_sensor(c2w_cv, camera, spp), seed=seed, spp=spp))
    # The film accumulates radiance only where rays hit something: colours are premultiplied by coverage.
    rgb = np.round(linear_to_srgb(image[..., :3]) * 255).astype(np.uint8)
    return rgb, np.clip(image[..., 3], 0.0, 1.0)


def render_view_rgba(scene: mi.Scene, c2w_cv: np.ndarray, camera: PinholeCamera, spp: int,
                     seed: int) -> np.ndarray:
    """Render one view as an sRGB ``uint8`` RGBA image with straight (not premultiplied) colour, the
    convention of PNG and of Blender's training sets: a NeRF can then learn opacity from the alpha
    channel instead of confusing a dark object with a transparent one on a black background."""
    image = np.array(mi.render(scene, sensor=_sensor(c2w_cv, camera, spp), seed=seed, spp=spp))
    alpha = np.clip(image[..., 3:], 0.0, 1.0)
    straight = np.where(alpha > 1e-6, image[..., :3] / np.maximum(alpha, 1e-6), 0.0)
    rgba = np.concatenate([linear_to_srgb(straight), alpha], -1)
    return np.round(rgba * 255).astype(np.uint8)


def distortion_padding(camera: PinholeCamera, dist_coeffs: np.ndarray) -> tuple[int, int]:
    """How far beyond the image the undistorted rays of its pixels reach, in pixels (x, y)."""
    w, h = camera.width, camera.height
    border = np.concatenate([
        np.stack([np.arange(w), np.zeros(w)], 1), np.stack([np.arange(w), np.full(w, h - 1)], 1),
        np.stack([np.zeros(h), np.arange(h)], 1), np.stack([np.full(h, w - 1), np.arange(h)], 1),
    ]).astype(np.float64)
    und = _undistort(border, camera.matrix, dist_coeffs, camera.matrix)
    pad_x = max(0.0, -und[:, 0].min(), und[:, 0].max() - (w - 1))
    pad_y = max(0.0, -und[:, 1].min(), und[:, 1].max() - (h - 1))
    return int(np.ceil(pad_x)) + 2, int(np.ceil(pad_y)) + 2


def distort_image(undistorted: np.ndarray, canvas: PinholeCamera, camera: PinholeCamera,
                  dist_coeffs: np.ndarray) -> np.ndarray:
    """Resample an ideal pinhole image rendered on ``canvas`` (the same focal length, padded) into what a
    lens with OpenCV distortion ``dist_coeffs`` would record through ``camera``.

    Each output pixel looks up where its ray lands in the ideal image: ``cv2.undistortPoints`` is the
    exact inverse of the distortion model, so undistorting the result recovers the ideal image.
    """
    ys, xs = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    pix = np.stack([xs.ravel(), ys.ravel()], 1)
    und = _undistort(pix, camera.matrix, dist_coeffs, canvas.matrix)
    map_x = und[:, 0].reshape(camera.height, camera.width).astype(np.float32)
    map_y = und[:, 1].reshape(camera.height, camera.width).astype(np.float32)
    return cv2.remap(undistorted, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _undistort(points: np.ndarray, matrix: np.ndarray, dist_coeffs: np.ndarray,
               new_matrix: np.ndarray) -> np.ndarray:
    """Ideal pixel positions (through ``new_matrix``) of distorted pixels [N, 2], iterated to 1e-10."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    src = np.ascontiguousarray(points, dtype=np.float64)[:, None]
    dist = np.asarray(dist_coeffs, dtype=np.float64)
    return cv2.undistortPointsIter(src, matrix, dist, None, new_matrix, criteria)[:, 0]
