"""The stability scenarios: one minimal clip per phenomenon (issue 15 §1), nothing the phenomenon does not need.

Every scenario is a function of a ``ScenarioBuilder`` (seeded rng, clip length T, image W x H). Sizes and
speeds are fractions of the view width at the subject's distance, so a clip looks the same at any
resolution: "6 % of the image width per frame" is 3.8 px/frame at W = 64. A light placed at the camera
casts no visible shadow (each shadow hides behind its caster), which keeps shadows out of scenarios that
are not about them. Events (camera cut, light switch) happen at frame T // 2.
"""
from __future__ import annotations

import numpy as np

from scenegen import geometry as geo
from scenegen.generate import _room_meshes
from scenegen.scenarios.builder import ScenarioBuilder, box_mesh, merged_boxes, translations
from scenegen.scenarios.registry import register_scenario

IRRADIANCE = 3.0          # irradiance (W/m^2) of a scenario's key light on its subject
SLOW = 0.06               # "slow" motion: fraction of the view width per frame
FAST = 0.25               # "fast" motion (tens of pixels per frame at W >= 64)
CAMERA_DISTANCE_M = 3.0   # camera to backdrop


def _backdrop(b: ScenarioBuilder, material: int, *, distance: float = CAMERA_DISTANCE_M, centre_y: float = 1.0,
              margin: float = 1.6) -> int:
    """A wall at z = 0 facing +z that fills the view of a camera ``distance`` metres in front of it."""
    half = 0.5 * margin * b.settings.view_width_m(distance)
    half_y = half * max(1.0, b.settings.height / b.settings.width)
    return b.quad("wall", [0.0, centre_y, 0.0], [half, 0.0, 0.0], [0.0, half_y, 0.0], [0.0, 0.0, 1.0], material)


def _floor(b: ScenarioBuilder, material: int, half: float = 3.0) -> int:
    return b.quad("floor", [0.0, 0.0, 0.0], [half, 0.0, 0.0], [0.0, 0.0, half], [0.0, 1.0, 0.0], material)


def _front_view(b: ScenarioBuilder) -> np.ndarray:
    """Static camera CAMERA_DISTANCE_M in front of the backdrop's centre; returns its origin (3,)."""
    origin = np.array([0.0, 1.0, CAMERA_DISTANCE_M])
    b.set_camera(origin, [0.0, 1.0, 0.0])
    return origin


def _sweeping_object(b: ScenarioBuilder, mesh_kind: str, fraction_per_frame: float, depth: float) -> int:
    """An object ``depth`` metres in front of the front-view camera moving along +x by ``fraction_per_frame``
    of the view width per frame, centred on the clip's middle frame; its size is 25 % of the view width."""
    s = b.settings
    width = s.view_width_m(depth)
    size = 0.25 * width
    mesh = box_mesh((size, size, size)) if mesh_kind == "box" else geo.draw_object_mesh(b.rng, mesh_kind, size)
    per_frame = translations([0.0, 1.0, CAMERA_DISTANCE_M - depth], [fraction_per_frame * width, 0.0, 0.0],
                             s.centred_steps())
    return b.shape("object", mesh, b.material("diffuse"), per_frame=per_frame, subject=True)


@register_scenario("disocclusion", focus=("disocclusion",))
def disocclusion(b: ScenarioBuilder) -> None:
    """A box sweeping slowly (6 % of the width per frame) across a textured wall; static camera."""
    camera = _front_view(b)
    _backdrop(b, b.textured(texel_pixels=16, distance=CAMERA_DISTANCE_M))
    _sweeping_object(b, "box", SLOW, depth=1.8)
    b.point_light("key", camera, IRRADIANCE * CAMERA_DISTANCE_M**2)


@register_scenario("moving_shadow", focus=("shadow",))
def moving_shadow(b: ScenarioBuilder) -> None:
    """A static post on a floor under a point light moving sideways: zero motion, a sweeping shadow."""
    s = b.settings
    b.set_camera([0.0, 2.6, 2.4], [0.0, 0.0, 0.0])
    _floor(b, b.material("diffuse"))
    b.shape("post", box_mesh((0.3, 0.7, 0.3)), b.material("diffuse"), [0.0, 0.35, 0.0], subject=True)
    height = 1.5
    steps = np.linspace(-1.0, 1.0, s.frames)
    path = np.stack([1.2 * steps, np.full(s.frames, height), np.full(s.frames, -0.4)], axis=1)
    b.point_light("key", path, IRRADIANCE * height**2)


@register_scenario("moving_reflection", focus=("specular",))
def moving_reflection(b: ScenarioBuilder) -> None:
    """A mirror and a glossy metal panel reflecting a box, under a sideways camera move (3 % width/frame)."""
    s = b.settings
    step = 0.03 * s.view_width_m(CAMERA_DISTANCE_M)
    x = step * s.centred_steps()
    zeros = np.zeros(s.frames)
    b.set_camera(np.stack([x, zeros + 1.0, zeros + CAMERA_DISTANCE_M], 1), np.stack([x, zeros + 0.6, zeros], 1),
                 path="truck")
    _floor(b, b.material("diffuse"))
    half = np.array([0.5, 0.0, 0.0]), np.array([0.0, 0.6, 0.0])
    b.quad("mirror", [-0.55, 0.62, 0.0], *half, [0.0, 0.0, 1.0], b.material("conductor"), subject=True)
    b.quad("glossy", [0.55, 0.62, 0.0], *half, [0.0, 0.0, 1.0], b.material("roughconductor", alpha=0.15),
           subject=True)
    b.shape("object", box_mesh((0.4, 0.4, 0.4)), b.material("diffuse"), [0.0, 0.2, 1.2])
    b.point_light("key", [0.0, 2.2, 1.8], IRRADIANCE * 4.0)
    b.fill_light(0.05)


@register_scenario("caustics", focus=("firefly", "transmission"), animated=False)
def caustics(b: ScenarioBuilder) -> None:
    """A glass sphere on a floor lit by a small bright panel behind it: a caustic seen as fireflies."""
    b.set_camera([0.0, 1.2, 2.2], [0.0, 0.25, 0.0])
    _floor(b, b.material("diffuse"))
    b.shape("glass", geo.draw_object_mesh(b.rng, "icosphere", 0.6), b.material("dielectric"), [0.0, 0.3, 0.0],
            subject=True)
    centre = np.array([0.0, 0.9, -0.9])
    normal = np.array([0.0, 0.3, 0.0]) - centre
    normal /= np.linalg.norm(normal)
    half_u = np.array([0.1, 0.0, 0.0])
    half_v = 0.1 * np.cross(normal, [1.0, 0.0, 0.0])
    b.quad("light", centre, half_u, half_v, normal, b.emissive(),
           emitter={"radiance": [60.0, 60.0, 60.0], "temperature_k": None})
    b.fill_light(0.02)


@register_scenario("camera_cut", focus=())
def camera_cut(b: ScenarioBuilder) -> None:
    """A box on a floor before a textured wall; the static camera cuts to a second view at frame T // 2."""
    s = b.settings
    first, second = np.array([0.0, 1.0, CAMERA_DISTANCE_M]), np.array([2.2, 1.6, 1.8])
    origins = np.where(np.arange(s.frames)[:, None] < s.event_frame, first, second)
    targets = np.where(np.arange(s.frames)[:, None] < s.event_frame, [0.0, 0.8, 0.0], [0.0, 0.5, 0.0])
    b.set_camera(origins, targets, cut_frame=s.event_frame)
    _backdrop(b, b.textured(texel_pixels=16, distance=CAMERA_DISTANCE_M), margin=3.0)
    _floor(b, b.material("diffuse"))
    b.shape("object", box_mesh((0.5, 0.5, 0.5)), b.material("diffuse"), [0.0, 0.25, 0.8], subject=True)
    b.point_light("key", [1.0, 2.5, 2.5], IRRADIANCE * 6.0)


@register_scenario("fast_motion", focus=("fast_motion", "disocclusion"))
def fast_motion(b: ScenarioBuilder) -> None:
    """A sphere crossing a textured wall at 25 % of the width per frame; static camera."""
    camera = _front_view(b)
    _backdrop(b, b.textured(texel_pixels=16, distance=CAMERA_DISTANCE_M))
    _sweeping_object(b, "icosphere", FAST, depth=1.8)
    b.point_light("key", camera, IRRADIANCE * CAMERA_DISTANCE_M**2)


@register_scenario("light_switch", focus=())
def light_switch(b: ScenarioBuilder) -> None:
    """A static box on a floor before a wall under a dim fill; a point light switches on at frame T // 2."""
    s = b.settings
    b.set_camera([0.0, 1.0, CAMERA_DISTANCE_M], [0.0, 0.6, 0.0])
    _backdrop(b, b.material("diffuse"))
    _floor(b, b.material("diffuse"))
    b.shape("object", box_mesh((0.5, 0.5, 0.5)), b.material("diffuse"), [0.0, 0.25, 0.8], subject=True)
    on = (np.arange(s.frames) >= s.event_frame).astype(np.float64)
    b.point_light("key", [0.8, 2.2, 2.0], IRRADIANCE * 6.0, intensity_scale_per_frame=on)
    b.fill_light(0.03)


@register_scenario("low_light", focus=("indirect_only",), animated=False)
def low_light(b: ScenarioBuilder) -> None:
    """A closed room lit by one narrow spot on a corner of the floor: most of the frame is lit indirectly."""
    room = np.array([4.0, 2.6, 4.0])
    walls = b.material("diffuse")
    for name, mesh, translation in _room_meshes(room):
        b.shape(name, mesh, walls, translation)
    b.set_camera([0.8, 1.3, 1.5], [-0.5, 0.9, -2.0])
    position, target = np.array([-1.2, 2.5, 0.2]), np.array([-1.4, 0.0, -1.4])
    b.spot_light("key", position, target, 8.0 * float(np.sum((target - position) ** 2)), cutoff_deg=12.0)


@register_scenario("thin_geometry", focus=("subject",))
def thin_geometry(b: ScenarioBuilder) -> None:
    """A grid of wires 0.4 px thick drifting slowly (1.5 % width/frame) before a plain wall."""
    s = b.settings
    camera = _front_view(b)
    _backdrop(b, b.material("diffuse"))
    depth = 1.5
    span, thickness = 0.6 * s.view_width_m(depth), 0.4 * s.pixel_size_m(depth)
    offsets = np.linspace(-span / 2, span / 2, 6)
    centres = np.concatenate([np.stack([offsets, 0 * offsets, 0 * offsets], 1),
                              np.stack([0 * offsets, offsets, 0 * offsets], 1)])
    extents = np.concatenate([np.tile([thickness, span, thickness], (6, 1)),
                              np.tile([span, thickness, thickness], (6, 1))])
    per_frame = translations([0.0, 1.0, CAMERA_DISTANCE_M - depth], [0.015 * s.view_width_m(depth), 0.0, 0.0],
                             s.centred_steps())
    b.shape("grid", merged_boxes(centres, extents, "wire_grid"), b.material("diffuse"), per_frame=per_frame,
            subject=True)
    b.point_light("key", camera, IRRADIANCE * CAMERA_DISTANCE_M**2)


@register_scenario("texture_motion", focus=("texture",))
def texture_motion(b: ScenarioBuilder) -> None:
    """A finely textured wall (one texture tile per 12 px) under a slow sideways camera move (3 % width/frame)."""
    s = b.settings
    x = 0.03 * s.view_width_m(CAMERA_DISTANCE_M) * s.centred_steps()
    zeros = np.zeros(s.frames)
    origins = np.stack([x, zeros + 1.0, zeros + CAMERA_DISTANCE_M], 1)
    b.set_camera(origins, np.stack([x, zeros + 1.0, zeros], 1), path="truck")
    _backdrop(b, b.textured(texel_pixels=12, distance=CAMERA_DISTANCE_M))
    b.point_light("key", [0.0, 1.0, CAMERA_DISTANCE_M], IRRADIANCE * CAMERA_DISTANCE_M**2)


@register_scenario("transparent", focus=("transmission",))
def transparent(b: ScenarioBuilder) -> None:
    """A glass sphere drifting slowly (3 % width/frame) in front of a detailed textured wall."""
    s = b.settings
    camera = _front_view(b)
    _backdrop(b, b.textured(texel_pixels=24, distance=CAMERA_DISTANCE_M))
    depth = 1.6
    size = 0.4 * s.view_width_m(depth)
    per_frame = translations([0.0, 1.0, CAMERA_DISTANCE_M - depth], [0.03 * s.view_width_m(depth), 0.0, 0.0],
                             s.centred_steps())
    b.shape("glass", geo.draw_object_mesh(b.rng, "icosphere", size), b.material("dielectric"),
            per_frame=per_frame, subject=True)
    b.point_light("key", camera, IRRADIANCE * CAMERA_DISTANCE_M**2)
