"""Keeping gradients through nerfstudio's image-rendering helpers.

``Model.get_outputs_for_camera_ray_bundle`` and ``Model.get_outputs_for_camera`` are decorated with
``torch.no_grad()``, and wrapping a call in ``torch.enable_grad()`` does not help because the decorator is
entered inside the call. The thesis' implementation renders through the former, so it needs them to keep
gradients; :func:`keep_gradients` does that for one model instance and undoes it on exit. The engine
itself renders through ``render.render_chunks`` and does not need this.
"""

import contextlib
import types
from collections.abc import Iterator

from nerfstudio.models.base_model import Model

PATCHED_METHODS = ("get_outputs_for_camera_ray_bundle", "get_outputs_for_camera")


@contextlib.contextmanager
def keep_gradients(model: Model) -> Iterator[Model]:
    """Within the block, ``model``'s no-grad rendering helpers run their undecorated bodies (so outputs
    carry gradients to the camera poses); other instances of the class are untouched, and the original
    behaviour returns on exit, also after an exception."""
    patched = []
    for name in PATCHED_METHODS:
        method = getattr(type(model), name, None)
        inner = getattr(method, "__wrapped__", None)  # the body under torch.no_grad()'s functools.wraps
        if inner is not None and name not in vars(model):
            setattr(model, name, types.MethodType(inner, model))
            patched.append(name)
    try:
        yield model
    finally:
        for name in patched:
            delattr(model, name)
