"""Mitsuba 3 scene descriptions: the Tango-like spacecraft, a texture-rich toy object, and a satellite with
thin parts (solar wings seen edge-on, a boom, a whip antenna) where a small NeRF has the least margin.

All scenes live in their body frame (the world frame of every label we write), sit on a black
background and are lit by one sun (a directional emitter fixed in the body frame, so that a NeRF trained
on them sees consistent lighting) plus a weak, hidden ambient term that keeps shadowed faces from being
pure black. Textures are generated from a seed, so a scene is a pure function of ``(name, seed)``.
"""

from typing import Literal

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")

SceneName = Literal["tango", "toy", "satellite"]

TANGO_KEYPOINTS = np.array(
    [
        [-0.3700, -0.3850, 0.3215],
        [-0.3700, 0.3850, 0.3215],
        [0.3700, 0.3850, 0.3215],
        [0.3700, -0.3850, 0.3215],
        [-0.3700, -0.2640, 0.0000],
        [-0.3700, 0.3040, 0.0000],
        [0.3700, 0.3040, 0.0000],
        [0.3700, -0.2640, 0.0000],
        [-0.5427, 0.4877, 0.2535],
        [0.5427, 0.4877, 0.2591],
        [0.3050, -0.5790, 0.2515],
    ]
)
"""The 11 public Tango keypoints in the body frame, metres (``tangoPoints.mat``, transposed)."""

PANEL_THICKNESS = 0.02
ANTENNA_RADIUS = 0.012
# Where each antenna leaves the body: inside the top corner region nearest its tip.
ANTENNA_BASES = np.array([[-0.30, 0.26, 0.2535], [0.30, 0.26, 0.2591], [0.26, -0.22, 0.2515]])

SUN_DIRECTION = np.array([-0.45, 0.35, -0.82])
"""Direction the sunlight travels in the body frame (towards -z: the sun sits above the solar panel)."""


def _box(lo: np.ndarray, hi: np.ndarray, bsdf: dict) -> dict:
    """An axis-aligned box between two corners (Mitsuba's ``cube`` spans [-1, 1]^3)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    to_world = mi.ScalarTransform4f().translate(centre.tolist()) @ mi.ScalarTransform4f().scale(half.tolist())
    return {"type": "cube", "to_world": to_world, "bsdf": bsdf}


def _bitmap(rgb: np.ndarray) -> dict:
    """A texture from a float RGB array in [0, 1] (linear), nearest filtering to keep edges crisp."""
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32)),
            "filter_type": "nearest", "raw": True}


def _foil_weight(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    """Blotchy crinkle pattern in [0, 1]: where foil reflects like metal and where it scatters."""
    noise = rng.random((size // 8, size // 8))
    noise = np.kron(noise, np.ones((8, 8)))
    noise += 0.5 * np.kron(rng.random((size // 4, size // 4)), np.ones((4, 4)))
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    return np.repeat(noise[..., None], 3, axis=2)


def _solar_cells(rng: np.random.Generator, cells: int = 6, px: int = 10) -> np.ndarray:
    """Dark blue cells with slight per-cell tint separated by light grid lines."""
    size = cells * px
    img = np.zeros((size, size, 3))
    for i in range(cells):
        for j in range(cells):
            tint = 0.02 * rng.standard_normal(3)
            img[i * px:(i + 1) * px, j * px:(j + 1) * px] = np.clip([0.03, 0.05, 0.22] + tint, 0, 1)
    img[::px, :] = img[:, ::px] = [0.55, 0.55, 0.6]
    return img


def _color_blocks(rng: np.random.Generator, blocks: int, px: int = 8) -> np.ndarray:
    """Random colour blocks, large enough to stay several pixels wide in 100-pixel images (as Lego's
    parts are): corners for SIFT that a small NeRF can still learn."""
    colors = rng.random((blocks, blocks, 3)) ** 1.5
    return np.kron(colors, np.ones((px, px, 1)))


def _lights(ambient: float) -> dict:
    sun = {"type": "directional", "direction": SUN_DIRECTION.tolist(),
           "irradiance": {"type": "rgb", "value": [3.0, 3.0, 3.0]}}
    sky = {"type": "constant", "radiance": {"type": "rgb", "value": [ambient] * 3}}
    return {"sun": sun, "ambient": sky}


def tango_scene(seed: int) -> dict:
    """Spacecraft after the public Tango geometry: foil-covered body, solar panel on top, three antennas
    whose tips are keypoints 9-11."""
    rng = np.random.default_rng(seed)
    foil = {
        "type": "blendbsdf",
        "weight": _bitmap(_foil_weight(rng)),
        "bsdf_0": {"type": "roughconductor", "material": "Au", "alpha": 0.35},
        "bsdf_1": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.55, 0.42, 0.12]}},
    }
    panel = {"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": _bitmap(_solar_cells(rng))}
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.8, 0.8]}}
    top = TANGO_KEYPOINTS[0, 2]
    shapes = {
        "body": _box([-0.37, -0.264, 0.0], [0.37, 0.304, top - PANEL_THICKNESS], foil),
        "panel": _box([-0.37, -0.385, top - PANEL_THICKNESS], [0.37, 0.385, top], panel),
    }
    for i, (base, tip) in enumerate(zip(ANTENNA_BASES, TANGO_KEYPOINTS[8:])):
        shapes[f"antenna{i}"] = {"type": "cylinder", "p0": base.tolist(), "p1": tip.tolist(),
                                 "radius": ANTENNA_RADIUS, "bsdf": white}
        shapes[f"antenna{i}_tip"] = {"type": "sphere", "center": tip.tolist(), "radius": ANTENNA_RADIUS,
                                     "bsdf": white}
    return {**shapes, **_lights(ambient=0.08)}


def toy_scene(seed: int) -> dict:
    """A texture-rich, clearly asymmetric tabletop object (our stand-in for Blender's Lego): a patterned
    base plate carrying a tall tower at one corner, a ball, a lying cylinder and a small cube."""
    rng = np.random.default_rng(seed)

    def textured(blocks: int) -> dict:
        return {"type": "diffuse", "reflectance": _bitmap(_color_blocks(rng, blocks))}

    return {
        "base": _box([-0.5, -0.4, -0.05], [0.5, 0.4, 0.0], textured(5)),
        "tower": _box([0.2, 0.1, 0.0], [0.45, 0.35, 0.6], textured(3)),
        "ball": {"type": "sphere", "center": [-0.25, 0.15, 0.15], "radius": 0.15, "bsdf": textured(4)},
        "log": {"type": "cylinder", "p0": [-0.4, -0.25, 0.08], "p1": [0.1, -0.25, 0.08], "radius": 0.08,
                "bsdf": textured(3)},
        "cube": _box([0.0, 0.0, 0.0], [0.12, 0.12, 0.12], textured(2)),
        **_lights(ambient=0.15),
    }


WING_THICKNESS = 0.01
BOOM_RADIUS = 0.008
SATELLITE_SPAN_M = 1.7
"""Wing tip to wing tip. No part is more than 0.87 m from the scene centre, so the SPEED+ field of view
holds the whole satellite in any attitude from the nearest training range (1.8 m across the short side at
4.5 m)."""


def satellite_scene(seed: int) -> dict:
    """A small satellite made of thin parts: a foil-covered bus with two solar wings 1 cm thick on thin yokes
    (1.7 m tip to tip, edge-on from some views), a 0.35 m boom with a magnetometer at its end, a dish and a
    whip antenna. Few pixels show most of it, as on the intricate satellites where nerfacto-tiny's margin over
    an all-black image was smallest (issue 12)."""
    rng = np.random.default_rng(seed)
    foil = {
        "type": "blendbsdf",
        "weight": _bitmap(_foil_weight(rng)),
        "bsdf_0": {"type": "roughconductor", "material": "Au", "alpha": 0.3},
        "bsdf_1": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.4, 0.15]}},
    }
    cells = {"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": _bitmap(_solar_cells(rng, cells=8))}
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.8, 0.8]}}
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.45, 0.45, 0.5]}}
    tip, half = SATELLITE_SPAN_M / 2, WING_THICKNESS / 2
    shapes = {"bus": _box([-0.25, -0.25, -0.3], [0.25, 0.25, 0.3], foil)}
    for side in (-1.0, 1.0):
        name = "wing_minus" if side < 0 else "wing_plus"
        inner, outer = sorted((side * 0.35, side * tip))
        shapes[name] = _box([-0.15, inner, 0.05 - half], [0.15, outer, 0.05 + half], cells)
        shapes[name + "_yoke"] = {"type": "cylinder", "p0": [0.0, side * 0.25, 0.05], "p1": [0.0, side * 0.35, 0.05],
                                  "radius": BOOM_RADIUS, "bsdf": grey}
    shapes["boom"] = {"type": "cylinder", "p0": [0.1, 0.1, 0.3], "p1": [0.1, 0.1, 0.65], "radius": BOOM_RADIUS,
                      "bsdf": white}
    shapes["magnetometer"] = _box([0.07, 0.07, 0.65], [0.13, 0.13, 0.71], grey)
    dish = mi.ScalarTransform4f().translate([-0.33, 0.0, -0.05]) @ mi.ScalarTransform4f().rotate([0, 1, 0], -90) \
        @ mi.ScalarTransform4f().scale(0.18)
    shapes["dish"] = {"type": "disk", "to_world": dish, "bsdf": {"type": "twosided", "bsdf": white}}
    shapes["dish_feed"] = {"type": "cylinder", "p0": [-0.25, 0.0, -0.05], "p1": [-0.33, 0.0, -0.05], "radius": 0.02,
                           "bsdf": grey}
    shapes["whip"] = {"type": "cylinder", "p0": [0.2, -0.2, -0.3], "p1": [0.4, -0.4, -0.5], "radius": BOOM_RADIUS,
                      "bsdf": white}
    return {**shapes, **_lights(ambient=0.08)}


def build_scene(name: SceneName, seed: int) -> dict:
    """Mitsuba scene dictionary (no sensor) for ``name``; pass it to :func:`mitsuba.load_dict`."""
    builders = {"tango": tango_scene, "toy": toy_scene, "satellite": satellite_scene}
    if name not in builders:
        raise ValueError(f"unknown scene {name!r}; choose one of {sorted(builders)}")
    objects = builders[name](seed)
    # Hidden emitters: the ambient term lights the object but the background stays black.
    integrator = {"type": "path", "max_depth": 4, "hide_emitters": True}
    return {"type": "scene", "integrator": integrator, **objects}


SCENE_CENTRES = {"tango": np.array([0.0, 0.0, 0.16]), "toy": np.array([0.0, 0.0, 0.15]),
                 "satellite": np.array([0.0, 0.0, 0.1])}
"""Point that training cameras look at (the middle of the object's bounding box)."""
