"""Seeded procedural scene generator: room, objects, materials, lights, camera clip -> manifest + files.

`generate_scene` writes `manifest.json`, `meshes/*.ply` and `textures/*.png` into a scene directory,
plus `textures/sky.exr` for open scenes (a ground plane under a procedural sky, or a room with one wall
missing; ``scenes.open_scene_prob``, see `open_scene`). Object placement lives in `scenegen.placement`.
Everything is drawn from numpy Generators spawned from one seed, and JSON floats are rounded to
FLOAT_DECIMALS, so the same inputs always give byte-identical files.
"""
from __future__ import annotations

import json
import logging
import math
import pathlib
import re
import shutil
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from scenegen import camera as cam
from scenegen import geometry as geo
from scenegen import lights
from scenegen import materials as mats
from scenegen.exr import write_exr
from scenegen.placement import Placer, draw_from_mix
from scenegen.textures import write_png

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
FLOAT_DECIMALS = 6
MAX_ATTEMPTS = 8
ROOM_WIDTH_RANGE_M = (4.0, 10.0)
ROOM_HEIGHT_RANGE_M = (2.5, 5.0)
OBJECT_SIZE_RANGE_M = (0.25, 1.1)
WALL_OVERLAP_M = 0.01  # walls extend past the room edges so corners are closed for every ray

EMISSIVE_OBJECT_PROB = 0.25
CONSTANT_FILL_PROB = 0.5
SPOT_PROB = 0.4  # probability that a non-area light is a spot rather than a point light

OPEN_KIND_MIX: dict[str, float] = {"ground": 0.5, "opening": 0.5}
"""Open scenes: objects on a ground plane under the sky (no walls, no ceiling), or the room with the
wall the camera faces most removed, looking out onto the ground plane and the sky."""
GROUND_HALF_EXTENT_M = 60.0  # the ground plane of open scenes reaches ~1 degree below the horizon
SKY_WEIGHT_RANGE: dict[str, tuple[float, float]] = {"ground": (1.5, 3.0), "opening": (0.5, 1.5)}
"""Weight of the sky in the irradiance shares (ceiling panels and small lights weigh 0.3-1.5 each)."""
OPEN_MIN_PITCH_FRACTION = 0.5
"""Open scenes: the camera looks no lower than this fraction of half the horizontal fov below the
horizon, so the sky fills roughly the top quarter of a square frame where nothing blocks it."""
SKY_FILE = "textures/sky.exr"

DEFAULT_SCENE_CFG: dict[str, Any] = {
    "objects": [5, 30],
    "camera_paths": list(cam.CAMERA_PATH_TYPES),
    "animated_light_prob": 0.35,
    "moving_objects_prob": 0.5,
    "camera_cut_prob": 0.2,
    "luminance_range": [0.05, 5.0],
    "open_scene_prob": 0.25,
}


@dataclass
class SceneDraft:
    """Everything drawn for one scene before it is written: manifest plus the files it references."""
    manifest: dict
    meshes: list[tuple[str, geo.ObjectMesh]] = field(default_factory=list)
    textures: list[tuple[str, np.ndarray]] = field(default_factory=list)
    environment_maps: list[tuple[str, np.ndarray]] = field(default_factory=list)  # (H, W, 3) float32


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------

def derive_seed(seed: int, attempt: int) -> int:
    """Seed for redraw `attempt` (>= 1) of a scene whose original seed is `seed`."""
    return int(np.random.SeedSequence([int(seed), int(attempt)]).generate_state(1, dtype=np.uint32)[0])


def _jsonable(value: Any) -> Any:
    """Recursively convert numpy values to Python types and round floats to FLOAT_DECIMALS."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        rounded = round(float(value), FLOAT_DECIMALS)
        return 0.0 if rounded == 0.0 else rounded  # no "-0.0" in the JSON
    return value


def open_scene(scene_id: str, open_prob: float, rng: np.random.Generator) -> bool:
    """Whether scene ``scene_id`` is drawn open (``open_prob`` = scenes.open_scene_prob).

    Scene k of a split (an id ending in ``_k``) is open when ceil((k + 1) p) > ceil(k p): exactly
    ceil(n p) of the first n scenes, evenly spread and starting with scene 0, whatever the seeds, so
    every split with p > 0 has an open scene. Other ids draw one uniform number from ``rng``."""
    match = re.search(r"_(\d+)$", scene_id)
    if match is None:
        return bool(rng.random() < open_prob)
    k = int(match.group(1))
    return math.ceil((k + 1) * open_prob - 1e-9) > math.ceil(k * open_prob - 1e-9)


# ---------------------------------------------------------------------------------------------
# Camera
# ---------------------------------------------------------------------------------------------

def _draw_camera(rng: np.random.Generator, cfg: dict, room_size: np.ndarray, n_frames: int,
                 keep_sky_in_view: bool = False) -> dict:
    """Draw fov, path(s) and an optional cut; returns the manifest 'camera' dict plus numpy arrays.
    In open scenes views are lifted to at most OPEN_MIN_PITCH_FRACTION * fov_x / 2 below the horizon."""
    path_types = list(cfg["camera_paths"])
    fov_x = float(rng.uniform(*cam.FOV_X_RANGE_DEG))
    first_kind = path_types[int(rng.integers(len(path_types)))]
    wants_cut = rng.random() < float(cfg["camera_cut_prob"])
    cut_frame = int(rng.integers(1, n_frames)) if (wants_cut and n_frames >= 2) else None
    first = cam.draw_camera_path(rng, first_kind, n_frames, room_size)
    origins, targets = first.origins.copy(), first.targets.copy()
    second: cam.CameraPath | None = None
    if cut_frame is not None:
        second_kind = path_types[int(rng.integers(len(path_types)))]
        second = cam.draw_camera_path(rng, second_kind, n_frames - cut_frame, room_size)
        origins[cut_frame:], targets[cut_frame:] = second.origins, second.targets
    if keep_sky_in_view:
        targets = cam.lift_low_views(origins, targets, -OPEN_MIN_PITCH_FRACTION * fov_x / 2)
    cut = np.zeros(n_frames, dtype=bool)
    if cut_frame is not None:
        cut[cut_frame] = True
    frames = [{"origin": origins[t], "target": targets[t], "up": [0.0, 1.0, 0.0], "fov_x_deg": fov_x,
               "cut": bool(cut[t])} for t in range(n_frames)]
    return {
        "manifest": {"fov_x_deg": fov_x, "path": first.kind, "speed": first.speed,
                     "path_after_cut": second.kind if second else None,
                     "speed_after_cut": second.speed if second else None,
                     "frames": frames},
        "origins": origins, "targets": targets, "cut": cut, "cut_frame": cut_frame,
    }


# ---------------------------------------------------------------------------------------------
# Scene drawing
# ---------------------------------------------------------------------------------------------

WALL_OUTWARD = {"wall_x_neg": np.array([-1.0, 0.0, 0.0]), "wall_x_pos": np.array([1.0, 0.0, 0.0]),
                "wall_z_neg": np.array([0.0, 0.0, -1.0]), "wall_z_pos": np.array([0.0, 0.0, 1.0])}


def _faced_wall(origins: np.ndarray, targets: np.ndarray) -> str:
    """The wall the camera faces most over the clip: largest mean horizontal view direction . outward normal."""
    view = (targets - origins)[:, [0, 2]]
    view = view / np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-9)
    mean = view.mean(axis=0)
    return max(WALL_OUTWARD, key=lambda name: float(mean @ WALL_OUTWARD[name][[0, 2]]))


def _room_meshes(room_size: np.ndarray, open_kind: str | None = None,
                 missing_wall: str | None = None) -> list[tuple[str, geo.ObjectMesh, np.ndarray]]:
    """Inward-facing quads (name, object-space mesh, world translation): floor, ceiling and four walls of
    a closed room; open scenes replace the floor by a GROUND_HALF_EXTENT_M ground plane and keep no walls
    or ceiling ('ground') or every surface but ``missing_wall`` ('opening')."""
    sx, sy, sz = room_size
    e = WALL_OVERLAP_M
    ex, ey, ez = np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    zero = np.zeros(3)
    specs = [
        ("floor", ex * (sx / 2 + e), ez * (sz / 2 + e), ey, np.array([0.0, 0.0, 0.0])),
        ("ceiling", ex * (sx / 2 + e), ez * (sz / 2 + e), -ey, np.array([0.0, sy, 0.0])),
        ("wall_x_neg", ez * (sz / 2 + e), ey * (sy / 2 + e), ex, np.array([-sx / 2, sy / 2, 0.0])),
        ("wall_x_pos", ez * (sz / 2 + e), ey * (sy / 2 + e), -ex, np.array([sx / 2, sy / 2, 0.0])),
        ("wall_z_neg", ex * (sx / 2 + e), ey * (sy / 2 + e), ez, np.array([0.0, sy / 2, -sz / 2])),
        ("wall_z_pos", ex * (sx / 2 + e), ey * (sy / 2 + e), -ez, np.array([0.0, sy / 2, sz / 2])),
    ]
    if open_kind is not None:
        ground = ("floor", ex * GROUND_HALF_EXTENT_M, ez * GROUND_HALF_EXTENT_M, ey, np.zeros(3))
        keep = () if open_kind == "ground" else tuple(spec for spec in specs[1:] if spec[0] != missing_wall)
        specs = [ground, *keep]
    return [(name, geo.quad_mesh(zero, hu, hv, n, kind="room"), t) for name, hu, hv, n, t in specs]


def draw_scene(scene_cfg: dict, seed: int, draw_seed: int, scene_id: str, n_frames: int) -> SceneDraft:
    """Draw a complete scene from `draw_seed` (no files written). See module docstring."""
    if n_frames < 1:
        raise ValueError("n_frames must be >= 1")
    cfg = {**DEFAULT_SCENE_CFG, **scene_cfg}
    # The seventh stream (open scenes) leaves the draws of closed scenes as they were before it existed.
    rng_room, rng_camera, rng_objects, rng_motion, rng_lights, rng_materials, rng_open = (
        np.random.default_rng(s) for s in np.random.SeedSequence(int(draw_seed)).spawn(7))
    open_kind: str | None = None
    if open_scene(scene_id, float(cfg["open_scene_prob"]), rng_open):
        open_kind = draw_from_mix(rng_open, OPEN_KIND_MIX)

    # Room ------------------------------------------------------------------------------------
    room_size = np.array([rng_room.uniform(*ROOM_WIDTH_RANGE_M), rng_room.uniform(*ROOM_HEIGHT_RANGE_M),
                          rng_room.uniform(*ROOM_WIDTH_RANGE_M)])
    room_size = np.round(room_size, 3)

    # Camera ----------------------------------------------------------------------------------
    camera = _draw_camera(rng_camera, cfg, room_size, n_frames, keep_sky_in_view=open_kind is not None)
    missing_wall = _faced_wall(camera["origins"], camera["targets"]) if open_kind == "opening" else None
    seg_start, seg_end = cam.clearance_segments(camera["origins"], camera["cut"])
    focus = camera["targets"].mean(axis=0)

    # Objects ---------------------------------------------------------------------------------
    n_min, n_max = (int(v) for v in cfg["objects"])
    n_objects = int(rng_objects.integers(n_min, n_max + 1))
    placer = Placer(room_size, seg_start, seg_end, focus)
    for _ in range(n_objects):
        kind = draw_from_mix(rng_objects, geo.OBJECT_SHAPE_MIX)
        size = rng_objects.uniform(*OBJECT_SIZE_RANGE_M)
        placer.place(rng_objects, geo.draw_object_mesh(rng_objects, kind, size))
    objects = placer.objects

    # Moving objects --------------------------------------------------------------------------
    moving: list[int] = []
    if n_frames > 1 and rng_motion.random() < float(cfg["moving_objects_prob"]):
        supporting = {o.support for o in objects if o.support is not None}
        candidates = [i for i, o in enumerate(objects) if o.placement != "stacked" and i not in supporting]
        wanted = int(rng_motion.integers(1, 4))
        for i in rng_motion.permutation(candidates).tolist():
            if len(moving) == wanted:
                break
            if placer.animate(rng_motion, int(i), n_frames):
                moving.append(int(i))
        moving.sort()

    # Per-frame object bounding spheres, to keep lights out of objects.
    sphere_centres = np.zeros((n_frames, len(objects), 3))  # (n_frames, n_objects, 3)
    for i, o in enumerate(objects):
        sphere_centres[:, i] = o.per_frame[:, :3, 3] if o.per_frame is not None else o.translation
    sphere_radii = np.array([o.mesh.bounding_radius for o in objects]).reshape(-1)

    # Lights ----------------------------------------------------------------------------------
    floor_area = float(room_size[0] * room_size[2])
    total_irradiance = float(np.exp(rng_lights.uniform(*np.log(lights.FLOOR_IRRADIANCE_RANGE))))
    n_panels = int(rng_lights.integers(1, 4))
    panels = lights.draw_ceiling_panels(rng_lights, room_size, n_panels) if open_kind != "ground" else []
    n_small = int(rng_lights.integers(0, 3))
    weights = np.concatenate([rng_lights.uniform(0.5, 1.5, len(panels)), rng_lights.uniform(0.3, 1.0, n_small)])
    sky_weight = float(rng_open.uniform(*SKY_WEIGHT_RANGE[open_kind])) if open_kind is not None else 0.0
    irradiance_share = total_irradiance * weights / (weights.sum() + sky_weight)
    light_lo, light_hi = lights.light_box(room_size)

    emitters: list[dict] = []
    for k in range(n_small):
        temperature = lights.draw_temperature(rng_lights)
        is_spot = rng_lights.random() < SPOT_PROB
        for _attempt in range(50):
            position = rng_lights.uniform(light_lo, light_hi)
            if lights.clear_of_spheres(position[None], sphere_centres.reshape(-1, 3),
                                       np.tile(sphere_radii, n_frames), 0.15):
                break
        share = irradiance_share[len(panels) + k]
        entry: dict[str, Any] = {"name": f"{'spot' if is_spot else 'point'}_{k}",
                                 "type": "spot" if is_spot else "point", "temperature_k": temperature,
                                 "position": position}
        if is_spot:
            cutoff = float(rng_lights.uniform(20.0, 50.0))
            if len(objects) and rng_lights.random() < 0.6:
                target = objects[int(rng_lights.integers(len(objects)))].translation.copy()
            else:
                target = np.array([rng_lights.uniform(-room_size[0] / 3, room_size[0] / 3), 0.0,
                                   rng_lights.uniform(-room_size[2] / 3, room_size[2] / 3)])
            entry.update({"target": target, "cutoff_angle": cutoff,
                          "beam_width": cutoff * float(rng_lights.uniform(0.5, 0.9)),
                          "intensity": lights.blackbody_rgb(temperature)
                          * lights.spot_intensity(share, floor_area, cutoff)})
        else:
            entry["intensity"] = lights.blackbody_rgb(temperature) * lights.point_intensity(share, floor_area)
        emitters.append(entry)
    sky_image: np.ndarray | None = None
    if open_kind is not None:
        # The sky replaces the constant fill; its scale is its share of the (unoccluded) floor irradiance.
        sky_image, sky_params = lights.draw_sky(rng_open)
        emitters.append({"name": "sky", "type": "envmap", "filename": SKY_FILE,
                         "scale": total_irradiance * sky_weight / (weights.sum() + sky_weight), **sky_params})
    elif rng_lights.random() < CONSTANT_FILL_PROB:
        temperature = lights.draw_temperature(rng_lights)
        # Closed room: this fill light only reaches the camera through walls removed by hand.
        emitters.append({"name": "fill", "type": "constant", "temperature_k": temperature,
                         "radiance": lights.blackbody_rgb(temperature) * rng_lights.uniform(0.01, 0.05)})

    panel_shapes: list[dict] = []
    for k, (centre, half) in enumerate(panels):
        temperature = lights.draw_temperature(rng_lights)
        radiance = lights.blackbody_rgb(temperature) * lights.panel_radiance(
            irradiance_share[k], floor_area, 4.0 * half[0] * half[1])
        panel_shapes.append({"name": f"light_panel_{k}", "centre": centre, "half": half,
                             "translation": np.array([centre[0], room_size[1] - 2e-3, centre[1]]),
                             "per_frame": None, "temperature_k": temperature, "radiance": radiance})

    emissive_object: int | None = None
    emissive_radiance: np.ndarray | None = None
    emissive_temperature: float | None = None
    small_objects = [i for i, o in enumerate(objects) if o.mesh.bounding_radius < 0.5]
    if small_objects and rng_lights.random() < EMISSIVE_OBJECT_PROB:
        emissive_object = small_objects[int(rng_lights.integers(len(small_objects)))]
        temperature = lights.draw_temperature(rng_lights)
        emissive_radiance = lights.blackbody_rgb(temperature) * rng_lights.uniform(1.5, 6.0)
        emissive_temperature = temperature

    # Animated light --------------------------------------------------------------------------
    animated_light: str | None = None
    if n_frames > 1 and rng_lights.random() < float(cfg["animated_light_prob"]):
        movable = [e for e in emitters if e["type"] in ("point", "spot")]
        if movable and rng_lights.random() < 0.5:
            light = movable[int(rng_lights.integers(len(movable)))]
            for _attempt in range(10):
                path = lights.draw_light_path(rng_lights, light["position"], n_frames, light_lo, light_hi)
                per_frame_clear = all(
                    lights.clear_of_spheres(path[t:t + 1], sphere_centres[t], sphere_radii, 0.15)
                    for t in range(n_frames))
                if per_frame_clear:
                    light["position_per_frame"] = path
                    del light["position"]
                    animated_light = light["name"]
                    break
        if animated_light is None and panel_shapes:
            panel = panel_shapes[int(rng_lights.integers(len(panel_shapes)))]
            half = panel["half"]
            # Slightly lower than the static panels so a moving panel never overlaps one coplanarly.
            start = panel["translation"] - np.array([0.0, 8e-3, 0.0])
            lo = np.array([-room_size[0] / 2 + half[0] + 0.1, start[1], -room_size[2] / 2 + half[1] + 0.1])
            hi = np.array([room_size[0] / 2 - half[0] - 0.1, start[1], room_size[2] / 2 - half[1] - 0.1])
            path = lights.draw_light_path(rng_lights, start, n_frames, lo, hi, vertical=False)
            panel["translation"] = path[0]
            panel["per_frame"] = np.stack([geo.make_transform(np.eye(3), p) for p in path])
            animated_light = panel["name"]

    # Materials, textures and shapes ------------------------------------------------------------
    draft = SceneDraft(manifest={})
    if sky_image is not None:
        draft.environment_maps.append((SKY_FILE, sky_image))
    material_entries: list[dict] = []
    shapes: list[dict] = []

    def add_material(mat_type: str, mix_is_wall: bool) -> int:
        name = f"mat_{len(material_entries):03d}"
        tex_path = f"textures/tex_{len(draft.textures):03d}.png"
        entry, image = mats.draw_material(
            rng_materials, name, mat_type, tex_path,
            mats.WALL_TEXTURE_PROB if mix_is_wall else mats.TEXTURE_PROB,
            allow_metallic=not mix_is_wall, value_range=(0.3, 0.85) if mix_is_wall else (0.1, 0.85))
        if image is not None:
            draft.textures.append((tex_path, image))
        material_entries.append(entry)
        return len(material_entries) - 1

    def add_shape(name: str, kind: str, mesh: geo.ObjectMesh, material: int, to_world: np.ndarray,
                  per_frame: np.ndarray | None, emitter: dict | None, extra: dict) -> None:
        mesh_path = f"meshes/{name}.ply"
        draft.meshes.append((mesh_path, mesh))
        shapes.append({"index": len(shapes), "name": name, "kind": kind, "mesh": mesh_path,
                       "material": material, "emitter": emitter, "to_world": to_world,
                       "to_world_per_frame": per_frame, "bounding_radius": mesh.bounding_radius,
                       "smooth": mesh.smooth, **extra})

    for name, mesh, translation in _room_meshes(room_size, open_kind, missing_wall):
        material = add_material(draw_from_mix(rng_materials, mats.WALL_MATERIAL_MIX), mix_is_wall=True)
        add_shape(name, "room", mesh, material, geo.make_transform(np.eye(3), translation), None, None,
                  {"object_type": None, "placement": None})

    for i, obj in enumerate(objects):
        emitter = None
        if i == emissive_object:
            material_entries.append(mats.emissive_material(
                f"mat_{len(material_entries):03d}", mats.draw_color(rng_materials, (0.6, 0.9), 0.3)))
            material = len(material_entries) - 1
            emitter = {"radiance": emissive_radiance, "temperature_k": emissive_temperature}
        else:
            material = add_material(draw_from_mix(rng_materials, mats.MATERIAL_MIX), mix_is_wall=False)
        add_shape(f"object_{i:03d}_{obj.mesh.kind}", "object", obj.mesh, material, obj.to_world,
                  obj.per_frame, emitter, {"object_type": obj.mesh.kind, "placement": obj.placement})
    object_shape_offset = len(shapes) - len(objects)
    moving_shapes = [object_shape_offset + i for i in moving]

    for panel in panel_shapes:
        material_entries.append(mats.emissive_material(f"mat_{len(material_entries):03d}", np.full(3, 0.8)))
        half = panel["half"]
        mesh = geo.quad_mesh(np.zeros(3), np.array([half[0], 0.0, 0.0]), np.array([0.0, 0.0, half[1]]),
                             np.array([0.0, -1.0, 0.0]), kind="light_panel")
        if panel["per_frame"] is not None:
            moving_shapes.append(len(shapes))
        add_shape(panel["name"], "light", mesh, len(material_entries) - 1,
                  geo.make_transform(np.eye(3), panel["translation"]), panel["per_frame"],
                  {"radiance": panel["radiance"], "temperature_k": panel["temperature_k"]},
                  {"object_type": None, "placement": "ceiling"})

    material_counts: dict[str, int] = {}
    for entry in material_entries:
        material_counts[entry["type"]] = material_counts.get(entry["type"], 0) + 1
    object_counts: dict[str, int] = {}
    for obj in objects:
        object_counts[obj.mesh.kind] = object_counts.get(obj.mesh.kind, 0) + 1

    manifest = {
        "format_version": FORMAT_VERSION,
        "scene_id": scene_id,
        "seed": int(seed),
        "draw_seed": int(draw_seed),
        "redraws": [],
        "n_frames": int(n_frames),
        "room": {"size": room_size, "open": open_kind, "missing_wall": missing_wall},
        "materials": material_entries,
        "shapes": shapes,
        "emitters": emitters,
        "camera": camera["manifest"],
        "animation": {"animated_light": animated_light, "moving_shapes": moving_shapes,
                      "camera_cut_frame": camera["cut_frame"]},
        "stats": {"n_objects": len(objects), "material_counts": material_counts,
                  "object_type_counts": object_counts, "n_area_panels": len(panel_shapes),
                  "n_point_spot_lights": n_small, "emissive_object": emissive_object is not None,
                  "target_floor_irradiance": total_irradiance, "preview_mean_luminance": None},
    }
    draft.manifest = _jsonable(manifest)
    return draft


# ---------------------------------------------------------------------------------------------
# Writing and the public entry point
# ---------------------------------------------------------------------------------------------

def write_manifest(manifest: dict, out_dir: pathlib.Path) -> None:
    """Write manifest.json with sorted keys (floats already rounded by the generator)."""
    text = json.dumps(_jsonable(manifest), sort_keys=True, indent=1)
    (out_dir / "manifest.json").write_text(text + "\n", encoding="utf-8")


def write_draft(draft: SceneDraft, out_dir: pathlib.Path) -> None:
    """Write the draft's meshes, textures and manifest, replacing any earlier meshes/ and textures/."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for sub in ("meshes", "textures"):
        if (out_dir / sub).exists():
            shutil.rmtree(out_dir / sub)
        (out_dir / sub).mkdir()
    for rel_path, mesh in draft.meshes:
        geo.export_ply(mesh, out_dir / rel_path)
    for rel_path, image in draft.textures:
        write_png(image, out_dir / rel_path)
    for rel_path, image in draft.environment_maps:
        write_exr(out_dir / rel_path, {c: image[..., k] for k, c in enumerate("RGB")})
    write_manifest(draft.manifest, out_dir)


def generate_scene(scene_cfg: dict, seed: int, scene_id: str, out_dir: pathlib.Path, n_frames: int,
                   luminance_check: Callable[[dict, pathlib.Path], float] | None = None) -> dict:
    """Draw a scene from `seed`; write manifest.json, meshes/*.ply, textures/*.png into out_dir; return the manifest.

    With `luminance_check` (a callable (manifest, scene_dir) -> mean preview luminance), scenes whose
    preview falls outside scene_cfg['luminance_range'] are redrawn from derived seeds (at most
    MAX_ATTEMPTS draws); every rejected draw is recorded in manifest['redraws']. If all draws fail,
    the one closest to the range (in log luminance) is kept and a warning is logged.
    """
    out_dir = pathlib.Path(out_dir)
    lum_lo, lum_hi = (float(v) for v in {**DEFAULT_SCENE_CFG, **scene_cfg}["luminance_range"])
    redraws: list[dict] = []

    def draw_and_write(draw_seed: int, preview: float | None) -> dict:
        draft = draw_scene(scene_cfg, seed, draw_seed, scene_id, n_frames)
        draft.manifest["redraws"] = _jsonable(redraws)
        draft.manifest["stats"]["preview_mean_luminance"] = _jsonable(preview)
        write_draft(draft, out_dir)
        return draft.manifest

    if luminance_check is None:
        return draw_and_write(int(seed), None)

    best: tuple[float, int, float] | None = None  # (distance to range, draw seed, luminance)
    for attempt in range(MAX_ATTEMPTS):
        draw_seed = int(seed) if attempt == 0 else derive_seed(seed, attempt)
        manifest = draw_and_write(draw_seed, None)
        luminance = float(luminance_check(manifest, out_dir))
        if np.isfinite(luminance) and lum_lo <= luminance <= lum_hi:
            manifest["stats"]["preview_mean_luminance"] = _jsonable(luminance)
            write_manifest(manifest, out_dir)
            return manifest
        if not np.isfinite(luminance):
            reason, distance = "non-finite preview luminance", np.inf
        elif luminance < lum_lo:
            reason = f"too dark: {luminance:.4g} < {lum_lo:g}"
            distance = np.log(lum_lo / max(luminance, 1e-12))
        else:
            reason, distance = f"too bright: {luminance:.4g} > {lum_hi:g}", np.log(luminance / lum_hi)
        log.info("scene %s attempt %d (seed %d) rejected: %s", scene_id, attempt, draw_seed, reason)
        redraws.append({"attempt": attempt, "seed": draw_seed,
                        "mean_luminance": luminance if np.isfinite(luminance) else None, "reason": reason})
        if best is None or distance < best[0]:
            best = (distance, draw_seed, luminance)

    assert best is not None
    log.warning("scene %s: no draw within luminance range [%g, %g] after %d attempts; keeping seed %d "
                "(luminance %.4g)", scene_id, lum_lo, lum_hi, MAX_ATTEMPTS, best[1], best[2])
    return draw_and_write(best[1], best[2] if np.isfinite(best[2]) else None)
