"""Where RGB training images surely show the object, and surely show empty space: what nerfacto-tiny is
taught about opacity when the images have no alpha.

Behind RGBA training images a random background teaches opacity: a ray that passes through a half-empty
surface, or through fog, shows the background's random colour and is penalised. Behind RGB images (an
object over black space, as SPEED+, SHIRT and cameras give them) the background must be black, and over
black a half-transparent surface in front of another looks the same as an opaque one in a mix of their
colours, and black fog the same as empty space. The toy trained that way rendered its tiles in colours
mixed with the tiles behind them, 1.0 dB below the same model trained with alpha and a random background
(docs/benchmarks.md).

The object's pixels are found as ``ns-invert`` finds the object in a frame (:func:`find_object`). Shrunk
by one pixel (a pixel on the outline is partly background), they are where the accumulation must be one.
Grown by two pixels, what lies outside them is where it must be zero: asking only for opacity on the object
let the model put black fog everywhere else, which cost nothing on the training views and hid the object in
the held-out ones (docs/benchmarks.md). The band between is left to the colour loss. A face in shadow, as
black as space, is therefore taught to be empty where it lies more than two pixels from a lit part; over
black it renders the same, and ``ns-invert``'s silhouette term finds no mask there either.
"""

from collections.abc import Iterable

import cv2
import numpy as np
import torch
from torch import Tensor

from nerfinv_plugin.initialization.detect import find_object

OBJECT, UNKNOWN, EMPTY = 1, -1, 0
"""Labels of :func:`opacity_labels`: accumulation one, nothing asked, accumulation zero."""


def opacity_labels(image: np.ndarray) -> np.ndarray:
    """[H, W] int8: OBJECT on the object found in ``image`` ([H, W, 3] float in [0, 1]) less its outline,
    EMPTY more than two pixels from it, UNKNOWN between; all UNKNOWN when no object is found (such a frame
    cannot say where the object is not: it may be cut off, or too dark to find)."""
    labels = np.full(image.shape[:2], UNKNOWN, np.int8)
    detection = find_object(image)
    if detection is None:
        return labels
    mask = detection.mask.astype(np.uint8)
    labels[cv2.dilate(mask, np.ones((5, 5), np.uint8)) == 0] = EMPTY
    labels[cv2.erode(mask, np.ones((3, 3), np.uint8)) == 1] = OBJECT
    return labels


def opacity_label_stack(images: Iterable[np.ndarray]) -> Tensor:
    """[N, H, W] int8: :func:`opacity_labels` of each image, padded with UNKNOWN to the largest size (a
    training ray's pixel indexes it as ``[image, row, column]``)."""
    labels = [opacity_labels(image) for image in images]
    height, width = max(m.shape[0] for m in labels), max(m.shape[1] for m in labels)
    padded = np.full((len(labels), height, width), UNKNOWN, np.int8)
    for padding, label in zip(padded, labels):
        padding[:label.shape[0], :label.shape[1]] = label
    return torch.from_numpy(padded)


def opacity_loss(labels: Tensor, accumulation: Tensor) -> Tensor:
    """Mean over the rays of ``(1 - accumulation)^2`` where ``labels`` [R] is OBJECT and ``accumulation^2``
    where it is EMPTY (``accumulation`` [R])."""
    target = (labels == OBJECT).to(accumulation.dtype)
    known = (labels != UNKNOWN).to(accumulation.dtype)
    return torch.mean(known * (accumulation - target) ** 2)
