"""How large the object is, read off the model's density: the radius of a sphere about the target centre
that holds everything the model made opaque around it.

Rays are bounded to that sphere during inversion (fewer samples, same image), and the view bank frames it,
so it must come from the model, not from a preset: a fixed bound cuts a larger object in half. Two passes
of a density grid: a coarse one over the model's scene box, then a fine one about what the coarse pass
found. Occupied cells are those with the density at which a ray loses a tenth of its light across a
coarse cell (one threshold for both passes: measured per fine cell, a model trained on RGB images kept
only its dense core, 0.29 m of a 0.8 m spacecraft); only the largest connected occupied region counts, so
floaters near the training cameras do not inflate the radius. Not the region nearest the centre: on one
user's-path spacecraft the cell nearest the centre was, at 8x the threshold, a lone speck apart from the
object, and the fine pass took it for the object (0.015 model units of 0.175; the view bank then framed
nothing). Cells that touch at an edge or a corner are connected: a boom or a panel edge that runs
diagonally through the grid is one thin chain of such cells, and with face contacts alone a fine pass cut
one user's-path spacecraft to its 0.17 m core.

A model trained on RGB images over black may also fill the space about the object with a thin dark fog
whose densest specks, above that threshold, touch one another and the object by chance: one such
nerfacto-tiny of the 0.73 m toy gave 2.57 m. An object's surface is sharp, so its radius barely changes
when the threshold doubles, while a chance-connected cloud of specks falls apart: the threshold is doubled
until the radius holds (docs/method.md).
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from nerfinv_plugin.model.loaded import LoadedModel, ModelLoadError
from nerfinv_plugin.model.render import RenderSettings

GRID = 48
"""Cells per axis of each pass."""
OPACITY = 0.1
"""Share of a ray's light that an occupied cell of the coarse pass absorbs across its width."""
MARGIN = 1.1
"""The radius found is widened by this factor, for the parts of thin structures below the threshold."""
STABLE = 1.15
"""A radius holds when doubling the threshold shrinks it by less than this factor."""
DOUBLINGS = 3
"""The threshold is doubled at most this many times (to 8x)."""
TOUCHING = np.ones((3, 3, 3), dtype=bool)
"""Cells that share a face, an edge or a corner are connected."""


def density_field(loaded: LoadedModel):
    """The field that gives the final densities: nerfacto's ``field``, NeRF's fine field."""
    for name in ("field", "field_fine"):
        field = getattr(loaded.model, name, None)
        if field is not None and hasattr(field, "density_fn"):
            return field
    raise ModelLoadError(f"{type(loaded.model).__name__} exposes no density field: give the object's size with "
                         "--render.target-radius-m METRES")


@dataclass(frozen=True)
class DensityGrid:
    """The model's density on a grid about the centre, to be thresholded (once per threshold tried)."""

    density: np.ndarray
    """[GRID, GRID, GRID] density at the cell centres."""
    distance: np.ndarray
    """[GRID, GRID, GRID] distance of each cell centre from the centre (model units)."""
    cell: float
    """Side of a cell (model units)."""

    @classmethod
    def measure(cls, loaded: LoadedModel, centre: Tensor, half: float) -> "DensityGrid":
        """The grid of half-side ``half`` about ``centre`` [3]."""
        field = density_field(loaded)
        axis = torch.linspace(-half, half, GRID, device=loaded.device)
        offsets = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        with torch.no_grad():
            points = offsets + centre.to(axis)
            density = torch.cat([field.density_fn(part).reshape(-1) for part in points.split(1 << 16)])
        if not bool(torch.isfinite(density).all()):
            raise ModelLoadError(f"{type(loaded.model).__name__} gives non-finite densities on a grid: give the "
                                 "object's size with --render.target-radius-m METRES")
        shape = (GRID, GRID, GRID)
        distance = np.linalg.norm((points - centre.to(axis)).reshape(*shape, 3).cpu().numpy(), axis=-1)
        return cls(density.reshape(shape).cpu().numpy(), distance, float(axis[1] - axis[0]))

    def occupied_radius(self, min_density: float) -> float | None:
        """Radius of the largest connected region of cells at least ``min_density`` dense; ``None`` when no
        cell is occupied."""
        occupied = self.density >= min_density
        if not occupied.any():
            return None
        labels, _ = ndimage.label(occupied, TOUCHING)
        largest = 1 + int(np.argmax(np.bincount(labels[occupied])[1:]))
        return float(self.distance[labels == largest].max()) + 0.5 * np.sqrt(3.0) * self.cell


def object_radius(loaded: LoadedModel, centre: Tensor) -> float:
    """Radius (model units) of a sphere about ``centre`` [3] (model frame) holding the object: at the
    lowest threshold from which doubling it changes the radius by less than ``STABLE``."""
    aabb = getattr(loaded.model, "scene_box", None)
    extent = float(aabb.aabb.abs().max()) if aabb is not None else 1.0
    min_density = base_density(extent)
    grids: dict[float, DensityGrid] = {}  # by half-side: the coarse pass is the same at every threshold

    def grid(half: float) -> DensityGrid:
        if half not in grids:
            grids[half] = DensityGrid.measure(loaded, centre, half)
        return grids[half]

    radius = _radius_at(grid, extent, min_density)
    if radius is None:
        raise ModelLoadError(f"the model's density is empty within {extent:.3g} model units of the target: is "
                             "--target the object's centre, and did the model learn it? (ns-invert-psnr scores it)")
    for doubling in range(1, DOUBLINGS + 1):
        denser = _radius_at(grid, extent, min_density * 2**doubling)
        if denser is None or radius <= STABLE * denser:
            break
        radius = denser
    return MARGIN * radius


def framed_radius(loaded: LoadedModel, centre: Tensor, settings: RenderSettings) -> float:
    """The object's radius (model units) about ``centre`` [3]: the sphere ``settings`` bound rays to, or,
    when they do not bound them, the extent read off the model's density."""
    if settings.target_sphere is not None:
        return float(settings.target_sphere[1])
    return object_radius(loaded, torch.as_tensor(centre, dtype=torch.float32, device=loaded.device))


def base_density(extent: float) -> float:
    """The lowest threshold: the density at which a ray loses ``OPACITY`` of its light across a coarse cell
    of a scene box of half-side ``extent``."""
    return float(-np.log(1.0 - OPACITY) / (2.0 * extent / (GRID - 1)))


def _radius_at(grid: Callable[[float], DensityGrid], extent: float, min_density: float) -> float | None:
    """The occupied radius at ``min_density``: a coarse pass over the scene box (half-side ``extent``), then a
    fine one about what it found (``grid(half)`` gives the density grid of that half-side); ``None`` when
    nothing is that dense."""
    coarse = grid(extent).occupied_radius(min_density)
    if coarse is None:
        return None
    fine = grid(min(1.25 * coarse, extent)).occupied_radius(min_density)
    return fine if fine is not None else coarse
