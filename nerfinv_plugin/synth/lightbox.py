"""Image-space degradations of a simulated lightbox camera: from a linear render to the 8-bit frame a lab
camera would deliver.

The values are fixed by issue 13 (before any loss was chosen, so the gap is not tuned to the method) and
live in :class:`LabCamera`. They are applied to the linear render (radiance, 1 = full scale of the sensor)
in the order light meets them, because the stages do not commute (bloom thresholds, noise depends on the
signal, gamma and JPEG are non-linear):

1. **Exposure x0.8**: the light the sensor collects; it comes first so that bloom's threshold and the
   shot noise see the exposed signal.
2. **Defocus blur** (Gaussian, sigma 1.0 px): the lens spreads each point before it reaches the sensor.
3. **Vignette**: the lens passes less light off axis; gain ``1 - 0.2 (r / r_corner)^2`` from the image
   centre, 0.8 at the corner pixels.
4. **Bloom**: the sensor's response to what lands on it; the excess above 0.85 (``max(I - 0.85, 0)``, per
   channel) spread by a Gaussian of sigma 2 px and added at 0.4.
5. **Noise** on the sensor signal: Gaussian read noise of sigma 0.015 plus shot noise of sigma
   ``0.04 sqrt(I)``, seeded.
6. **Clip to [0, 1]**: the sensor's range (noise on the black background is clipped at 0, which lifts it).
7. **Display gamma 2.0** (``v = I^(1/2)``) instead of the training renders' sRGB curve (about 2.2), then
   rounding to 8 bits.
8. **JPEG at quality 75** when written (:func:`encode_jpeg`).

Lens distortion, when the trajectories have it, is applied to the linear render before step 1: it is the
geometry of the same lens. This is a simulation of a hardware-in-the-loop facility, not the facility.
"""

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class LabCamera:
    """The lightbox camera's degradations. The defaults are issue 13's and are what ``ns-invert-synth``
    uses; a neutral value (exposure 1, blur 0, vignette 1, bloom 0, noise 0) turns a stage off, which is
    how the tests look at one stage at a time."""

    exposure: float = 0.8
    """Scale on the linear signal."""
    defocus_sigma_px: float = 1.0
    """Sigma of the Gaussian defocus blur, pixels; 0: none."""
    vignette_corner: float = 0.8
    """Gain at the corner pixels (1 at the centre, quadratic in the radius); 1: none."""
    bloom_threshold: float = 0.85
    """Linear level above which light blooms."""
    bloom_sigma_px: float = 2.0
    """Sigma of the Gaussian that spreads the excess above the threshold, pixels."""
    bloom_strength: float = 0.4
    """Weight of the spread excess added back; 0: no bloom."""
    read_noise: float = 0.015
    """Sigma of the Gaussian read noise, on [0, 1]."""
    shot_noise: float = 0.04
    """Shot noise sigma is ``shot_noise * sqrt(I)``, on [0, 1]."""
    gamma: float = 2.0
    """Display gamma of the encoding ``v = I^(1 / gamma)``."""
    jpeg_quality: int = 75
    """JPEG quality of the written frames."""


LIGHTBOX = LabCamera()
"""Issue 13's lightbox camera."""


def vignette_gain(height: int, width: int, corner: float) -> np.ndarray:
    """[H, W] float32 gain, 1 at the image centre falling as the squared radius to ``corner`` at the corner
    pixel centres (pixel centres at integer coordinates, centre at ((W - 1) / 2, (H - 1) / 2))."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = (xs - (width - 1) / 2) ** 2 + (ys - (height - 1) / 2) ** 2
    r2_corner = ((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2
    return (1.0 - (1.0 - corner) * r2 / max(r2_corner, 1e-12)).astype(np.float32)


def _gaussian(image: np.ndarray, sigma: float) -> np.ndarray:
    # Reflected borders: the blur neither darkens nor brightens the frame's edge.
    return cv2.GaussianBlur(image, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)


def degrade(linear: np.ndarray, rng: np.random.Generator, camera: LabCamera = LIGHTBOX) -> np.ndarray:
    """Steps 1-7 of the module docstring: ``linear`` [H, W, 3] radiance (float, 1 = full scale, may exceed
    1) to the lab camera's RGB ``uint8`` frame [H, W, 3]; the noise is drawn from ``rng``."""
    signal = np.asarray(linear, dtype=np.float32)
    if signal.ndim != 3 or signal.shape[2] != 3:
        raise ValueError(f"expected a linear RGB image [H, W, 3], got shape {signal.shape}")
    signal = signal * np.float32(camera.exposure)
    if camera.defocus_sigma_px > 0:
        signal = _gaussian(signal, camera.defocus_sigma_px)
    signal = signal * vignette_gain(*signal.shape[:2], camera.vignette_corner)[..., None]
    if camera.bloom_strength > 0:
        excess = np.maximum(signal - np.float32(camera.bloom_threshold), 0.0)
        signal = signal + np.float32(camera.bloom_strength) * _gaussian(excess, camera.bloom_sigma_px)
    sigma = np.sqrt(camera.read_noise ** 2 + camera.shot_noise ** 2 * np.maximum(signal, 0.0))
    signal = signal + sigma * rng.standard_normal(signal.shape, dtype=np.float32)
    encoded = np.power(np.clip(signal, 0.0, 1.0), 1.0 / camera.gamma)
    return np.round(encoded * 255.0).astype(np.uint8)


def encode_jpeg(rgb: np.ndarray, camera: LabCamera = LIGHTBOX) -> bytes:
    """Step 8: the JPEG file of an RGB ``uint8`` frame at the lab camera's quality."""
    ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, camera.jpeg_quality])
    if not ok:
        raise OSError("OpenCV could not encode a JPEG")
    return encoded.tobytes()
