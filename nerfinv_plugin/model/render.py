"""Rendering a loaded model at camera poses in the model frame (camera-to-world, OpenGL camera axes).

The engine renders N candidate poses at the same P target pixels in every iteration. Here those N x P
rays are built as one ray bundle (so the field runs on large batches, which is what makes a CPU or GPU
efficient) and split into chunks whose size follows a memory budget. Gradients flow to the poses; the
model's weights are frozen by the loader, so no memory or time goes into gradients for them.

Two entry points:
- :func:`render` returns outputs for all rays, differentiable, for callers that need them together;
- :func:`render_chunks` yields them chunk by chunk, so that a caller can back-propagate each chunk's loss
  before rendering the next and keep memory bounded by one chunk (the engine does this).
"""

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import psutil
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import scale_gradients_by_distance_squared
from nerfstudio.models.base_model import Model
from nerfstudio.models.nerfacto import NerfactoModel
from nerfstudio.models.splatfacto import SplatfactoModel
from torch import Tensor

from nerfinv_plugin.model.loaded import LoadedModel, ModelLoadError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in nerfstudio's convention: pixel (row i, col j) is sampled at (j + 0.5,
    i + 0.5), so a centred principal point is cx = W / 2. OpenCV's cx is half a pixel less."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_opencv(cls, matrix: np.ndarray, width: int, height: int) -> "Intrinsics":
        m = np.asarray(matrix, dtype=np.float64)
        return cls(float(m[0, 0]), float(m[1, 1]), float(m[0, 2]) + 0.5, float(m[1, 2]) + 0.5, width, height)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera at another resolution (focal lengths and principal point scale with it)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)


class RenderOutput(NamedTuple):
    """Per-ray outputs, shaped [..., 3] / [..., 1]; ``None`` where the model has no such output. Inversion
    compares colours and silhouettes; depths are not rendered."""

    rgb: Tensor
    accumulation: Tensor | None


# Vanilla NeRF and mip-NeRF name their outputs per sampling level; the fine level is the answer.
_OUTPUT_NAMES = {"rgb": ("rgb", "rgb_fine"), "accumulation": ("accumulation", "accumulation_fine")}


def _pick(outputs: dict[str, Tensor], kind: str) -> Tensor | None:
    for name in _OUTPUT_NAMES[kind]:
        if name in outputs:
            return outputs[name]
    return None


def as_3x4(c2w: Tensor) -> Tensor:
    """Accept [N, 3, 4] or [N, 4, 4] camera-to-world poses; return the [N, 3, 4] part."""
    if c2w.ndim != 3 or c2w.shape[-2:] not in ((3, 4), (4, 4)):
        raise ValueError(f"camera-to-world poses must be [N, 3, 4] or [N, 4, 4], got {tuple(c2w.shape)}")
    return c2w[:, :3, :4]


def _check_pixels(pixels: Tensor, intrinsics: Intrinsics) -> None:
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must be [P, 2] (row, col), got {tuple(pixels.shape)}")
    if len(pixels) and (pixels.min() < 0 or (pixels[:, 0] >= intrinsics.height).any()
                        or (pixels[:, 1] >= intrinsics.width).any()):
        raise ValueError(f"pixels fall outside the {intrinsics.width}x{intrinsics.height} image")


def pinhole_cameras(c2w: Tensor, intrinsics: Intrinsics) -> Cameras:
    """nerfstudio cameras for poses [N, 3, 4] sharing one set of pinhole intrinsics."""
    return Cameras(camera_to_worlds=c2w, fx=float(intrinsics.fx), fy=float(intrinsics.fy), cx=float(intrinsics.cx),
                   cy=float(intrinsics.cy), width=intrinsics.width, height=intrinsics.height,
                   camera_type=CameraType.PERSPECTIVE)


def ray_bundle(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor) -> RayBundle:
    """One flat ray bundle for ``pixels`` [P, 2] (row, col) seen from every pose in ``c2w`` [N, 3|4, 4]:
    ray ``n * P + p`` is pixel ``p`` of pose ``n``; differentiable with respect to ``c2w``.

    The rays of nerfstudio's pinhole camera (``Cameras.generate_rays`` for an undistorted perspective camera,
    what every model here was trained with): the same origins, unit directions, pixel areas and direction
    norms to float rounding (tested), computed once per pixel in the camera frame and turned by each pose.
    nerfstudio's general camera code (distortion, other camera types, per-ray intrinsics) took a tenth of an
    inversion iteration for these few thousand rays."""
    c2w = as_3x4(c2w)
    _check_pixels(pixels, intrinsics)
    n, p = c2w.shape[0], pixels.shape[0]
    coords = pixels.to(c2w.device, torch.float32) + 0.5
    x = (coords[:, 1] - intrinsics.cx) / intrinsics.fx
    y = (coords[:, 0] - intrinsics.cy) / intrinsics.fy
    minus_one = torch.full_like(x, -1.0)
    # Camera-frame directions (OpenGL: y up, looking down -z) at the pixel and one pixel right and down of it,
    # whose distances give nerfstudio's pixel area.
    camera = torch.stack([torch.stack([x, -y, minus_one], -1),
                          torch.stack([x + 1.0 / intrinsics.fx, -y, minus_one], -1),
                          torch.stack([x, -(y + 1.0 / intrinsics.fy), minus_one], -1)])  # [3, P, 3]
    world = torch.einsum("nij,kpj->knpi", c2w[:, :, :3], camera).reshape(3, n * p, 3)
    norm = torch.linalg.vector_norm(world, dim=-1, keepdim=True)  # at least 1: the camera-frame z is -1
    directions = world / norm
    dx = torch.linalg.vector_norm(directions[0] - directions[1], dim=-1)
    dy = torch.linalg.vector_norm(directions[0] - directions[2], dim=-1)
    origins = c2w[:, :, 3].repeat_interleave(p, 0)
    # Models index per-image embeddings by camera; in eval mode they use the mean, so any valid index works.
    return RayBundle(origins=origins, directions=directions[0], pixel_area=(dx * dy)[:, None],
                     camera_indices=torch.zeros(n * p, 1, dtype=torch.long, device=c2w.device),
                     metadata={"directions_norm": norm[0].detach()})


MIN_NEAR = 0.05
"""Nearest sample distance (model units) when a sphere bounds the rays: a camera inside the sphere must
not sample its own lens."""


@dataclass(frozen=True, eq=False)
class RenderSettings:
    """How a render samples the loaded model's rays, passed to every render call: the model itself stays
    as it was loaded. Built by :func:`render_settings` (``ns-invert``'s ``--render`` options resolve into one
    in :func:`nerfinv_plugin.inversion.session.bound_rays`)."""

    target_sphere: tuple[Tensor, float] | None = None
    """(centre [3], radius) in the model frame of a sphere holding the whole target, when known: rays are
    sampled only where they cross it, and rays that miss it are background without being rendered
    (see :func:`bound_to_target`). ``None``: the model's near and far planes."""
    proposal_samples: tuple[int, ...] | None = None
    """Samples per ray of each proposal level (nerfacto and its kin). ``None``: as the model has them."""
    nerf_samples: int | None = None
    """Samples per ray of the final field. ``None``: as the model has them."""
    chunk_rays: int | None = None
    """Rays rendered per chunk. ``None``: ``loaded.chunk_rays``, measured when the model was loaded."""


AS_TRAINED = RenderSettings()
"""The model's own near/far planes, sample counts and chunk size."""


def render_settings(loaded: LoadedModel, target_sphere: tuple[Tensor, float] | None = None,
                    proposal: tuple[int, ...] | None = None, nerf: int | None = None) -> RenderSettings:
    """Settings that bound rays to ``target_sphere`` and take ``proposal`` / ``nerf`` samples per ray
    (``None``: as the model has them), checked against the model; when sample counts change, the chunk
    size is measured again under them (it follows the memory a ray takes)."""
    sphere = None if target_sphere is None else (target_sphere[0].to(loaded.device), target_sphere[1])
    settings = RenderSettings(sphere, None if proposal is None else tuple(proposal), nerf)
    if proposal is None and nerf is None:
        return settings
    sampler = getattr(loaded.model, "proposal_sampler", None)
    if sampler is None:
        raise ModelLoadError(f"{type(loaded.model).__name__} has no proposal sampler: its sample counts cannot be "
                             "changed; leave --render.proposal-samples and --render.nerf-samples unset")
    if proposal is not None and len(proposal) != len(sampler.num_proposal_samples_per_ray):
        raise ModelLoadError(f"this model has {len(sampler.num_proposal_samples_per_ray)} proposal levels; "
                             f"--render.proposal-samples got {len(proposal)} numbers")
    return replace(settings, chunk_rays=check_renders(loaded, settings))


def sample_counts(loaded: LoadedModel, settings: RenderSettings) -> tuple[tuple[int, ...], int] | None:
    """(proposal samples per level, nerf samples) a render under ``settings`` takes; ``None`` for a model
    without a proposal sampler."""
    sampler = getattr(loaded.model, "proposal_sampler", None)
    if sampler is None:
        return None
    proposal = settings.proposal_samples
    return (tuple(sampler.num_proposal_samples_per_ray) if proposal is None else tuple(proposal),
            sampler.num_nerf_samples_per_ray if settings.nerf_samples is None else settings.nerf_samples)


@contextmanager
def _sampling(loaded: LoadedModel, settings: RenderSettings) -> Iterator[None]:
    """Within the block, the model's proposal sampler takes ``settings``' sample counts (nerfstudio reads
    them off the sampler while it renders); on exit, also after an exception, it has its own again."""
    if settings.proposal_samples is None and settings.nerf_samples is None:
        yield
        return
    sampler = loaded.model.proposal_sampler
    saved = sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray
    try:
        if settings.proposal_samples is not None:
            sampler.num_proposal_samples_per_ray = tuple(settings.proposal_samples)
        if settings.nerf_samples is not None:
            sampler.num_nerf_samples_per_ray = settings.nerf_samples
        yield
    finally:
        sampler.num_proposal_samples_per_ray, sampler.num_nerf_samples_per_ray = saved


def bound_to_target(settings: RenderSettings, bundle) -> Tensor | None:
    """Limit each ray's samples to where it crosses ``settings.target_sphere`` (setting the bundle's nears
    and fars, which nerfstudio's colliders then leave alone) and return the mask of rays that cross it;
    ``None`` when no sphere is set. The same number of samples then covers the target's depth, not the
    whole scene's, so fewer samples give the same image. The depths are not differentiated (nerfacto's
    sample depths are detached too); gradients reach the pose through the ray origins and directions."""
    if settings.target_sphere is None:
        return None
    centre, radius = settings.target_sphere
    with torch.no_grad():
        origins, directions = bundle.origins, bundle.directions
        along = ((centre.to(origins) - origins) * directions).sum(-1, keepdim=True)
        closest2 = ((centre.to(origins) - origins) ** 2).sum(-1, keepdim=True) - along**2
        half = torch.sqrt(torch.clamp(radius**2 - closest2, min=0.0))
        hits = (closest2 < radius**2) & (along + half > MIN_NEAR)
        bundle.nears = torch.clamp(along - half, min=MIN_NEAR)
        bundle.fars = torch.maximum(along + half, bundle.nears + 1e-4)
    return hits[:, 0]


def background_colour(loaded: LoadedModel) -> Tensor | None:
    """The colour a ray that meets nothing renders to, when the model makes it a constant: nerfacto and
    friends render 'random' and 'black' as black in eval mode. ``None`` when it depends on the ray."""
    renderer = getattr(loaded.model, "renderer_rgb", None)
    colour = getattr(renderer, "background_color", None)
    if isinstance(colour, Tensor):
        return colour.to(loaded.device, torch.float32)
    if colour in ("random", "black"):
        return torch.zeros(3, device=loaded.device)
    if colour == "white":
        return torch.ones(3, device=loaded.device)
    return None


def _chunk_rays(loaded: LoadedModel, settings: RenderSettings) -> int:
    """Rays per chunk: the settings', else the one measured when the model was loaded, else measured now."""
    return settings.chunk_rays if settings.chunk_rays is not None else loaded.chunk_rays or check_renders(loaded)


Rays = slice | Tensor
"""Which of the N * P flat rays a chunk holds: a slice, or indices when rays were skipped."""


def render_chunks(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor,
                  settings: RenderSettings = AS_TRAINED) -> Iterator[tuple[Rays, RenderOutput]]:
    """Render ``ray_bundle(...)`` under ``settings`` in chunks of at most ``settings.chunk_rays`` rays.
    Yields ``(rays, outputs for them)``, ``rays`` indexing the N * P flat rays; every ray is accounted for.
    With a target sphere set, the rays that miss it come last, as one chunk of background colour that
    does not depend on the pose."""
    chunk_rays = _chunk_rays(loaded, settings)
    if chunk_rays < 1:
        raise ValueError(f"chunk_rays must be at least 1, got {chunk_rays}")
    if isinstance(loaded.model, SplatfactoModel):
        yield from _splat_chunks(loaded, c2w, intrinsics, pixels)
        return
    bundle = ray_bundle(loaded, c2w.to(loaded.device), intrinsics, pixels)
    hits = bound_to_target(settings, bundle)
    background = background_colour(loaded)
    if hits is None or background is None or bool(hits.all()):
        order: Tensor | None = None
        rendered = len(bundle)
    else:
        order = torch.cat([torch.nonzero(hits).flatten(), torch.nonzero(~hits).flatten()])
        rendered = int(hits.sum())
        bundle = bundle[order]
    for start in range(0, rendered, chunk_rays):
        part = slice(start, min(start + chunk_rays, rendered))
        with _sampling(loaded, settings):
            out = _outputs(loaded.model, bundle[part])
        yield (part if order is None else order[part]), out
    if order is not None and rendered < len(order):
        missed = order[rendered:]
        count = len(missed)
        yield missed, RenderOutput(background.expand(count, 3), torch.zeros(count, 1, device=loaded.device))


def _outputs(model: Model, bundle) -> RenderOutput:
    """Colour and accumulation of ``bundle`` through ``model.forward``. For nerfacto (whose ``get_outputs`` is
    nerfacto's own) the same collider, sampler, field and renderers are called in the same order, without the
    median depth, expected depth and per-proposal depths it renders besides: the same numbers (tested), with
    fewer operators per chunk."""
    if (isinstance(model, NerfactoModel) and type(model).get_outputs is NerfactoModel.get_outputs
            and not model.training and not model.config.predict_normals):
        if model.collider is not None:
            bundle = model.collider(bundle)
        samples, _, _ = model.proposal_sampler(bundle, density_fns=model.density_fns)
        field = model.field.forward(samples, compute_normals=False)
        if model.config.use_gradient_scaling:
            field = scale_gradients_by_distance_squared(field, samples)
        weights = samples.get_weights(field[FieldHeadNames.DENSITY])
        return RenderOutput(model.renderer_rgb(rgb=field[FieldHeadNames.RGB], weights=weights),
                            model.renderer_accumulation(weights=weights))
    outputs = model(bundle)
    rgb = _pick(outputs, "rgb")
    if rgb is None:
        raise RuntimeError(f"{type(model).__name__} returned no rgb output (keys: {sorted(outputs)})")
    return RenderOutput(rgb, _pick(outputs, "accumulation"))


def _splat_chunks(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics,
                  pixels: Tensor) -> Iterator[tuple[slice, RenderOutput]]:
    """Gaussian splatting renders whole images from a camera, not rays: rasterize each candidate's image
    (differentiable in the pose through the view matrix) and take the chosen pixels. One candidate per
    chunk."""
    c2w = as_3x4(c2w).to(loaded.device)
    _check_pixels(pixels, intrinsics)
    rows, cols = pixels[:, 0].to(loaded.device), pixels[:, 1].to(loaded.device)
    p = pixels.shape[0]
    for n in range(c2w.shape[0]):
        outputs = loaded.model.get_outputs(pinhole_cameras(c2w[n:n + 1], intrinsics))
        picked = {name: value[rows, cols] for name, value in outputs.items()
                  if isinstance(value, Tensor) and value.ndim == 3}
        yield slice(n * p, (n + 1) * p), RenderOutput(picked["rgb"], picked.get("accumulation"))


def render(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor,
           settings: RenderSettings = AS_TRAINED) -> RenderOutput:
    """Colours (and accumulation where the model has it) of ``pixels`` [P, 2] (row, col) from
    every pose in ``c2w`` [N, 3|4, 4] under ``settings``: ``rgb`` is [N, P, 3]. Differentiable with respect
    to ``c2w``."""
    n, p = as_3x4(c2w).shape[0], pixels.shape[0]
    parts = list(render_chunks(loaded, c2w, intrinsics, pixels, settings))

    def join(field: str, channels: int) -> Tensor | None:
        values = [getattr(out, field) for _, out in parts]
        if any(v is None for v in values):
            return None
        if all(isinstance(rays, slice) for rays, _ in parts):
            return torch.cat(values).reshape(n, p, channels)
        index = torch.cat([torch.arange(n * p, device=loaded.device)[rays] if isinstance(rays, slice) else rays
                           for rays, _ in parts])
        joined = torch.cat(values)
        return joined[torch.argsort(index)].reshape(n, p, channels)

    return RenderOutput(join("rgb", 3), join("accumulation", 1))


def render_image(loaded: LoadedModel, c2w_model: np.ndarray, intrinsics: Intrinsics,
                 settings: RenderSettings = AS_TRAINED) -> np.ndarray:
    """Full image [H, W, 3] in [0, 1] at one pose [4, 4] under ``settings``, without gradients: for
    evaluation and plots."""
    rows, cols = torch.meshgrid(torch.arange(intrinsics.height), torch.arange(intrinsics.width), indexing="ij")
    pixels = torch.stack([rows.reshape(-1), cols.reshape(-1)], 1)
    c2w = torch.as_tensor(np.asarray(c2w_model)[None], dtype=torch.float32)
    with torch.no_grad():
        rgb = render(loaded, c2w, intrinsics, pixels, settings).rgb
    return rgb.reshape(intrinsics.height, intrinsics.width, 3).clamp(0, 1).cpu().numpy()


def bytes_per_ray(loaded: LoadedModel, settings: RenderSettings = AS_TRAINED, probe_rays: int = 64) -> float:
    """Memory one ray holds until its backward pass: the tensors autograd saves, counted while rendering
    a probe batch whose poses require gradients. Device-agnostic, unlike allocator statistics."""
    saved = 0

    def pack(tensor: Tensor) -> Tensor:
        nonlocal saved
        saved += tensor.numel() * tensor.element_size()
        return tensor

    c2w = torch.eye(4, device=loaded.device)[None, :3].clone()
    c2w[0, 2, 3] = 4.0  # any pose works: the count depends on sample counts, not on the scene
    c2w.requires_grad_(True)
    side = int(math.ceil(math.sqrt(probe_rays)))
    intrinsics = Intrinsics(side, side, side / 2, side / 2, side, side)
    rows, cols = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    pixels = torch.stack([rows.reshape(-1), cols.reshape(-1)], 1)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = render(loaded, c2w, intrinsics, pixels, replace(settings, chunk_rays=side * side)).rgb
    return (saved + out.numel() * out.element_size()) / (side * side)


def memory_budget_bytes(device: torch.device) -> int:
    """Memory a chunk may hold: half of what is free on a GPU, a quarter of available RAM on a CPU
    (other processes and the rest of the engine need the remainder)."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free * 0.5)
    return int(psutil.virtual_memory().available * 0.25)


MAX_CHUNK_RAYS = 1 << 16
"""Larger chunks stop paying off and would make a single chunk's latency long."""


CUDA_ONLY = {"NGPModel": "nerfacc's CUDA ray marching", "SplatfactoModel": "gsplat's CUDA rasterizer"}
"""Models known to render only on CUDA: refused at once on other devices (probing them on a CPU first
tries to compile CUDA extensions, for over a minute, before failing)."""


def check_renders(loaded: LoadedModel, settings: RenderSettings = AS_TRAINED) -> int:
    """Render a probe batch under ``settings`` with gradients and return the chunk size (rays) the memory
    budget allows under them; nothing is written to ``loaded``. A model that cannot render on its device
    (a CUDA-only kernel on a CPU, say) fails here with one line naming the model and the device instead
    of deep inside the first iteration."""
    name = type(loaded.model).__name__
    for base in type(loaded.model).__mro__:
        if base.__name__ in CUDA_ONLY and loaded.device.type != "cuda":
            raise ModelLoadError(f"{name} ({loaded.config.method_name}) cannot render on {loaded.device}: it needs "
                                 f"{CUDA_ONLY[base.__name__]}; use a CUDA machine or a nerfacto model")
    try:
        per_ray = bytes_per_ray(loaded, settings)
    except Exception as err:  # noqa: BLE001 - any failure here means the same thing to the user
        first = (str(err).splitlines() or [""])[0][:200]
        raise ModelLoadError(f"{name} ({loaded.config.method_name}) cannot render on {loaded.device}: "
                             f"{type(err).__name__}: {first}") from err
    # Twice the saved tensors: forward transients live alongside them for a moment.
    return int(max(1, min(MAX_CHUNK_RAYS, memory_budget_bytes(loaded.device) // (2 * per_ray))))


class RayJacobians(NamedTuple):
    """Colours of N x P rays and each ray's colour derivatives with respect to its own origin and direction:
    what a Gauss-Newton step needs to build the Jacobian of the residuals with respect to any pose
    parameterisation (a pose moves a ray's origin and direction, nothing else)."""

    rgb: Tensor
    """[N, P, 3] rendered colours (no graph)."""
    d_origin: Tensor
    """[N, P, 3, 3]: ``d_origin[n, p, c]`` is the gradient of colour channel ``c`` with respect to the origin."""
    d_direction: Tensor
    """[N, P, 3, 3]: the same with respect to the (unit) direction."""
    origins: Tensor
    """[N, P, 3] ray origins (model frame)."""
    directions: Tensor
    """[N, P, 3] unit ray directions."""


def render_ray_jacobians(loaded: LoadedModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor,
                         settings: RenderSettings = AS_TRAINED) -> RayJacobians:
    """Render ``pixels`` [P, 2] from every pose in ``c2w`` [N, 4, 4] with the per-ray Jacobians of the colours.
    A ray's colour depends on its own origin and direction only, so one backward pass per colour channel over
    all rays at once gives every ray's 3 x 6 Jacobian exactly (three backward passes, not one per residual).
    Rays that miss ``settings.target_sphere`` are background: zero derivatives."""
    if isinstance(loaded.model, SplatfactoModel):
        raise ModelLoadError("splatfacto renders whole images, not rays: use --optimizer.method adam with it")
    chunk_rays = _chunk_rays(loaded, settings)
    n, p = c2w.shape[0], pixels.shape[0]
    with torch.no_grad():
        bundle = ray_bundle(loaded, c2w.detach().to(loaded.device), intrinsics, pixels)
        hits = bound_to_target(settings, bundle)
    origins, directions = bundle.origins.detach(), bundle.directions.detach()
    background = background_colour(loaded)
    rgb = torch.zeros(n * p, 3, device=loaded.device)
    d_origin = torch.zeros(n * p, 3, 3, device=loaded.device)
    d_direction = torch.zeros(n * p, 3, 3, device=loaded.device)
    if hits is not None and background is not None:
        rgb[~hits] = background
        rendered = torch.nonzero(hits).flatten()
    else:
        rendered = torch.arange(n * p, device=loaded.device)
    for start in range(0, len(rendered), chunk_rays):
        rays = rendered[start:start + chunk_rays]
        part = bundle[rays]
        part.origins = origins[rays].clone().requires_grad_(True)
        part.directions = directions[rays].clone().requires_grad_(True)
        with _sampling(loaded, settings), torch.enable_grad():
            colour = _outputs(loaded.model, part).rgb
            for c in range(3):
                if not colour.requires_grad:  # nothing on these rays depends on the pose
                    break
                g_origin, g_direction = torch.autograd.grad(colour[:, c].sum(), (part.origins, part.directions),
                                                            retain_graph=c < 2, allow_unused=True)
                if g_origin is not None:
                    d_origin[rays, c] = g_origin
                if g_direction is not None:
                    d_direction[rays, c] = g_direction
        rgb[rays] = colour.detach()
    return RayJacobians(rgb.reshape(n, p, 3), d_origin.reshape(n, p, 3, 3), d_direction.reshape(n, p, 3, 3),
                        origins.reshape(n, p, 3), directions.reshape(n, p, 3))
