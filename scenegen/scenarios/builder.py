"""Building blocks of the stability scenarios: a small scene builder over the generator's own pieces.

A scenario is written in the procedural manifest format (``scenegen.generate``), so the renderer, the
motion vectors and every later stage read it unchanged. The builder only adds what a scenario asks for:
materials from ``scenegen.materials`` (drawn from the scenario's generator, then pinned where the
phenomenon needs a property, e.g. a glossy roughness), meshes from ``scenegen.geometry`` (quads, boxes,
icospheres), point / spot / constant lights and per-frame camera poses. Sizes and speeds are given in
pixels of the configured image (``ScenarioSettings.pixel_size_m``), so a phenomenon keeps its size in
the image when ``stability.width`` changes. Units: metres, y up; intensities linear RGB.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import trimesh

from scenegen import geometry as geo
from scenegen import lights
from scenegen import materials as mats
from scenegen.generate import FORMAT_VERSION, SceneDraft, _jsonable
from scenegen.textures import draw_texture, mean_linear_albedo

FOV_X_DEG = 40.0
WHITE_K = 6500.0   # colour temperature of the scenarios' lights


@dataclass(frozen=True)
class ScenarioSettings:
    """What a scenario function may depend on: its scene id, seed, clip length and image size (pixels)."""

    scene_id: str
    seed: int
    frames: int
    width: int
    height: int

    @property
    def event_frame(self) -> int:
        """The frame of a scenario's single event (camera cut, light switch): the middle of the clip."""
        return self.frames // 2

    def view_width_m(self, distance: float, fov_x_deg: float = FOV_X_DEG) -> float:
        """Width (m) of the pinhole view at ``distance`` metres in front of the camera."""
        return 2.0 * distance * math.tan(math.radians(fov_x_deg) / 2.0)

    def pixel_size_m(self, distance: float, fov_x_deg: float = FOV_X_DEG) -> float:
        """Footprint (m) of one pixel at ``distance`` metres (image centre)."""
        return self.view_width_m(distance, fov_x_deg) / self.width

    def centred_steps(self) -> np.ndarray:
        """(T,) frame offsets t - (T - 1) / 2: a motion of v per frame is centred on the clip's middle."""
        return np.arange(self.frames) - (self.frames - 1) / 2.0


def box_mesh(extents: tuple[float, float, float], kind: str = "box") -> geo.ObjectMesh:
    """Flat-shaded axis-aligned box centred on the origin, ``extents`` (3,) in metres."""
    mesh = trimesh.creation.box(extents=np.asarray(extents, dtype=np.float64))
    return geo.ObjectMesh(kind, np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), False)


def merged_boxes(centres: np.ndarray, extents: np.ndarray, kind: str) -> geo.ObjectMesh:
    """One flat-shaded mesh of N boxes: ``centres`` (N, 3), ``extents`` (N, 3) metres (e.g. a wire grid)."""
    parts = [trimesh.creation.box(extents=e, transform=geo.make_transform(np.eye(3), c))
             for c, e in zip(centres, extents)]
    mesh = trimesh.util.concatenate(parts)
    vertices = np.asarray(mesh.vertices, np.float64)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return geo.ObjectMesh(kind, vertices - 0.5 * (lo + hi), np.asarray(mesh.faces, np.int64), False)


def translations(start: np.ndarray, velocity: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(T, 4, 4) rigid transforms translating to ``start + velocity * steps[t]`` (no rotation)."""
    return np.stack([geo.make_transform(np.eye(3), np.asarray(start) + np.asarray(velocity) * s) for s in steps])


@dataclass
class ScenarioBuilder:
    """Accumulates one scenario's materials, shapes, lights and camera; ``finish`` returns the SceneDraft."""

    settings: ScenarioSettings
    rng: np.random.Generator
    materials: list[dict] = field(default_factory=list)
    shapes: list[dict] = field(default_factory=list)
    emitters: list[dict] = field(default_factory=list)
    camera: dict | None = None
    cut_frame: int | None = None
    subjects: list[int] = field(default_factory=list)
    draft: SceneDraft = field(default_factory=lambda: SceneDraft(manifest={}))

    # Materials ------------------------------------------------------------------------------------
    def _add_material(self, entry: dict, image: np.ndarray | None = None) -> int:
        entry = {**entry, "name": f"mat_{len(self.materials):03d}"}
        if image is not None:
            self.draft.textures.append((entry["texture"], image))
        self.materials.append(entry)
        return len(self.materials) - 1

    def material(self, mat_type: str, **params: Any) -> int:
        """A material of ``mat_type`` drawn by scenegen.materials (untextured), with ``params`` pinned in its
        Mitsuba params (``alpha`` also sets the recorded roughness)."""
        entry, _ = mats.draw_material(self.rng, "", mat_type, "", 0.0, value_range=(0.3, 0.8))
        entry["params"].update(params)
        if "alpha" in params:
            entry["roughness"] = float(params["alpha"])
        return self._add_material(entry)

    def textured(self, texel_pixels: float, distance: float) -> int:
        """A diffuse material with a procedural texture (scenegen.textures, pattern drawn from the rng),
        scaled so that one texture tile covers ``texel_pixels`` image pixels at ``distance`` metres."""
        path = f"textures/tex_{len(self.draft.textures):03d}.png"
        # A dark and a bright colour: the pattern is detail a denoiser must keep, whatever colours are drawn.
        image, _ = draw_texture(self.rng, mats.draw_color(self.rng, (0.05, 0.25)), mats.draw_color(self.rng, (0.6, 0.9)))
        tiles_per_m = 1.0 / (texel_pixels * self.settings.pixel_size_m(distance))
        to_uv = np.diag([tiles_per_m, tiles_per_m, 1.0, 1.0]).tolist()
        entry = {"type": "diffuse", "params": {"type": "diffuse", "reflectance": {
                     "type": "bitmap", "filename": path, "to_uv": to_uv}},
                 "albedo": mean_linear_albedo(image).tolist(), "roughness": 1.0, "metallic": False,
                 "transmissive": False, "emissive": False, "texture": path}
        return self._add_material(entry, image)

    def emissive(self) -> int:
        return self._add_material(mats.emissive_material("", np.full(3, 0.8)))

    # Shapes ---------------------------------------------------------------------------------------
    def shape(self, name: str, mesh: geo.ObjectMesh, material: int, position: np.ndarray | None = None, *,
              per_frame: np.ndarray | None = None, emitter: dict | None = None, subject: bool = False) -> int:
        """Add a shape (index = its G-buffer object id); ``per_frame`` (T, 4, 4) makes it move rigidly."""
        index = len(self.shapes)
        to_world = per_frame[0] if per_frame is not None else geo.make_transform(
            np.eye(3), np.zeros(3) if position is None else np.asarray(position, np.float64))
        mesh_path = f"meshes/{name}.ply"
        self.draft.meshes.append((mesh_path, mesh))
        self.shapes.append({"index": index, "name": name, "kind": "light" if emitter else "object",
                            "mesh": mesh_path, "material": material, "emitter": emitter, "to_world": to_world,
                            "to_world_per_frame": per_frame, "bounding_radius": mesh.bounding_radius,
                            "smooth": mesh.smooth, "object_type": mesh.kind, "placement": None})
        if subject:
            self.subjects.append(index)
        return index

    def quad(self, name: str, centre: np.ndarray, half_u: np.ndarray, half_v: np.ndarray, normal: np.ndarray,
             material: int, **kwargs: Any) -> int:
        """A rectangle facing ``normal`` (one-sided emitters emit along it), centred at ``centre``."""
        mesh = geo.quad_mesh(np.zeros(3), np.asarray(half_u, float), np.asarray(half_v, float),
                             np.asarray(normal, float), kind="quad")
        return self.shape(name, mesh, material, np.asarray(centre, float), **kwargs)

    # Lights ---------------------------------------------------------------------------------------
    def point_light(self, name: str, position: np.ndarray, intensity: float, *,
                    intensity_scale_per_frame: np.ndarray | None = None) -> None:
        """Isotropic point light; ``position`` (3,) or (T, 3) per frame; ``intensity`` in W/sr (white);
        ``intensity_scale_per_frame`` (T,) multiplies it per frame (0 = off)."""
        rgb = lights.blackbody_rgb(WHITE_K) * intensity
        entry: dict[str, Any] = {"name": name, "type": "point", "temperature_k": WHITE_K, "intensity": rgb}
        position = np.asarray(position, np.float64)
        entry["position_per_frame" if position.ndim == 2 else "position"] = position
        if intensity_scale_per_frame is not None:
            entry["intensity_per_frame"] = np.outer(intensity_scale_per_frame, rgb)
        self.emitters.append(entry)

    def spot_light(self, name: str, position: np.ndarray, target: np.ndarray, intensity: float,
                   cutoff_deg: float) -> None:
        self.emitters.append({"name": name, "type": "spot", "temperature_k": WHITE_K, "position": position,
                              "target": target, "cutoff_angle": cutoff_deg, "beam_width": 0.8 * cutoff_deg,
                              "intensity": lights.blackbody_rgb(WHITE_K) * intensity})

    def fill_light(self, radiance: float) -> None:
        """A constant environment: dim light from every direction (what a closed scene would bounce)."""
        self.emitters.append({"name": "fill", "type": "constant", "temperature_k": WHITE_K,
                              "radiance": lights.blackbody_rgb(WHITE_K) * radiance})

    # Camera ---------------------------------------------------------------------------------------
    def set_camera(self, origins: np.ndarray, targets: np.ndarray, *, cut_frame: int | None = None,
                   path: str = "static", fov_x_deg: float = FOV_X_DEG) -> None:
        """Per-frame camera: ``origins``, ``targets`` (3,) for a static camera or (T, 3)."""
        n = self.settings.frames
        origins = np.broadcast_to(np.asarray(origins, np.float64), (n, 3))
        targets = np.broadcast_to(np.asarray(targets, np.float64), (n, 3))
        frames = [{"origin": origins[t], "target": targets[t], "up": [0.0, 1.0, 0.0], "fov_x_deg": fov_x_deg,
                   "cut": t == cut_frame} for t in range(n)]
        self.camera = {"fov_x_deg": fov_x_deg, "path": path, "speed": None, "path_after_cut": None,
                       "speed_after_cut": None, "frames": frames}
        self.cut_frame = cut_frame

    # Result ---------------------------------------------------------------------------------------
    def finish(self, scenario: str, focus: tuple[str, ...], description: str) -> SceneDraft:
        """The scenario's SceneDraft: a procedural-format manifest plus a ``stability`` record (scenario,
        focus masks, subject shapes, events known from the manifest)."""
        if self.camera is None:
            raise ValueError(f"scenario {scenario!r} set no camera")
        n = self.settings.frames
        moving = [s["index"] for s in self.shapes if s["to_world_per_frame"] is not None]
        animated = next((e["name"] for e in self.emitters if "position_per_frame" in e), None)
        events = []
        if self.cut_frame is not None:
            events.append({"frame": int(self.cut_frame), "kind": "camera_cut"})
        for emitter in self.emitters:
            if "intensity_per_frame" in emitter:
                power = np.asarray(emitter["intensity_per_frame"]).sum(axis=1)
                for t in range(1, n):
                    if power[t] != power[t - 1]:
                        events.append({"frame": t, "kind": "light_switch", "light": emitter["name"],
                                       "on": bool(power[t] > power[t - 1])})
        manifest = {
            "format_version": FORMAT_VERSION, "kind": "stability", "scene_id": self.settings.scene_id,
            "seed": self.settings.seed, "draw_seed": self.settings.seed, "redraws": [], "n_frames": n,
            "room": {"size": [0.0, 0.0, 0.0], "open": None, "missing_wall": None},
            "materials": self.materials, "shapes": self.shapes, "emitters": self.emitters, "camera": self.camera,
            "animation": {"animated_light": animated, "moving_shapes": moving,
                          "camera_cut_frame": self.cut_frame},
            "stability": {"scenario": scenario, "description": description, "focus": list(focus),
                          "subject_shapes": self.subjects, "events": sorted(events, key=lambda e: e["frame"]),
                          "width": self.settings.width, "height": self.settings.height},
            "stats": {"n_objects": len(self.shapes), "preview_mean_luminance": None},
        }
        self.draft.manifest = _jsonable(manifest)
        return self.draft
