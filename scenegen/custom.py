"""Bring-your-own scenes: a Mitsuba 3 XML file plus a camera path from the config.

``import_custom_scene`` writes a manifest in the procedural scenes' format (``"kind": "custom"``)
holding the XML's path and hash, one static entry per shape and the per-frame camera, so the
render, motion-vector and evaluation code treat custom scenes like generated ones.
``load_custom_frame_scene`` loads the XML, keeps its shapes and emitters, and swaps in the
project's integrator and the frame's sensor. Material features (roughness, metallic,
transmissive) are read from each BSDF's class and parameters and stored as per-face attributes,
which exist only on meshes: analytic shapes (sphere, disk, cylinder) report them as 0 and are
listed in the manifest's ``shapes_without_material_features``.

Camera paths (speeds relative to the scene's bounding-box diagonal D, per frame):
dolly -- translate along the view direction by 0.01 D; orbit -- rotate about the target around
``up`` by 2 degrees; pan -- rotate the view direction about ``up`` by 1 degree; spline -- orbit
by 1.5 degrees with a smooth vertical sway of amplitude 0.02 D.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
from pathlib import Path

import numpy as np

IDENTITY = np.eye(4).tolist()
log = logging.getLogger("scenegen")
_scene_cache: dict[str, object] = {}


class CustomSceneError(ValueError):
    """A custom scene's XML cannot be used; the message names the file."""


def _load_xml(xml: Path):
    import mitsuba as mi

    key = str(Path(xml).resolve())
    if key not in _scene_cache:
        if not Path(key).is_file():
            raise CustomSceneError(f"custom scene XML not found: {key}")
        try:
            _scene_cache[key] = mi.load_file(key)
        except Exception as exc:  # noqa: BLE001 -- Mitsuba raises RuntimeError with parser details
            raise CustomSceneError(f"cannot load custom scene XML {key}: {exc}") from exc
    return _scene_cache[key]


def _rotate_about(vector: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of ``vector`` (3,) about unit ``axis`` by ``angle`` radians."""
    axis = axis / np.linalg.norm(axis)
    return (vector * math.cos(angle) + np.cross(axis, vector) * math.sin(angle)
            + axis * np.dot(axis, vector) * (1.0 - math.cos(angle)))


def camera_path(kind: str, origin: np.ndarray, target: np.ndarray, up: np.ndarray, n_frames: int,
                scale: float) -> list[dict]:
    """Per-frame {origin, target, up, cut} of a camera path (see the module docstring)."""
    frames = []
    forward = (target - origin) / max(np.linalg.norm(target - origin), 1e-9)
    for t in range(n_frames):
        if kind == "dolly":
            o, g = origin + 0.01 * scale * t * forward, target + 0.01 * scale * t * forward
        elif kind == "orbit":
            o, g = target + _rotate_about(origin - target, up, math.radians(2.0) * t), target
        elif kind == "pan":
            o, g = origin, origin + _rotate_about(target - origin, up, math.radians(1.0) * t)
        elif kind == "spline":
            sway = 0.02 * scale * math.sin(2.0 * math.pi * t / max(n_frames, 2))
            o = target + _rotate_about(origin - target, up, math.radians(1.5) * t) + sway * up
            g = target
        else:
            raise CustomSceneError(f"unknown camera path {kind!r}; allowed: dolly, orbit, pan, spline")
        frames.append({"origin": [round(float(v), 6) for v in o], "target": [round(float(v), 6) for v in g],
                       "up": [float(v) for v in up], "cut": False})
    return frames


def import_custom_scene(entry: dict, scene_id: str, out_dir: Path) -> dict:
    """Write ``out_dir/manifest.json`` for the extra_scenes ``entry``; return the manifest."""
    import mitsuba as mi

    xml = Path(entry["xml"]).resolve()
    scene = _load_xml(xml)
    sensors = scene.sensors()
    params = mi.traverse(sensors[0]) if sensors else {}
    to_world = np.array(params["to_world"].matrix, np.float64).reshape(4, 4) if sensors else np.eye(4)
    bbox = scene.bbox()
    lo, hi = np.array(bbox.min, np.float64), np.array(bbox.max, np.float64)
    diagonal = float(np.linalg.norm(hi - lo)) if np.all(np.isfinite(hi - lo)) else 1.0
    camera = entry["camera"]
    origin = np.asarray(camera.get("origin", to_world[:3, 3]), np.float64)
    if "target" in camera:
        target = np.asarray(camera["target"], np.float64)
    else:
        forward = to_world[:3, 2] / np.linalg.norm(to_world[:3, 2])
        target = origin + forward * max(float(np.dot(0.5 * (lo + hi) - origin, forward)), 1.0)
    up = np.asarray(camera.get("up", [0.0, 1.0, 0.0]), np.float64)
    fov = float(camera.get("fov_deg", float(params["x_fov"][0]) if sensors and "x_fov" in params else 45.0))
    n_frames = int(entry["frames"])
    shapes = [{"index": i, "name": shape.id() or f"shape_{i:03d}", "kind": "custom", "mesh": None,
               "material": None, "emitter": None, "to_world": IDENTITY, "to_world_per_frame": None,
               "material_features": isinstance(shape, mi.Mesh)}
              for i, shape in enumerate(scene.shapes())]
    without = [shape["name"] for shape in shapes if not shape["material_features"]]
    if without:
        # Per-face attributes only exist on meshes: analytic shapes report roughness 0, metallic 0,
        # transmissive 0 and shape index 0 (static scenes only, so motion vectors are unaffected).
        log.warning("custom scene %s: %d non-mesh shapes without material features: %s", scene_id,
                    len(without), ", ".join(without))
    manifest = {
        "format_version": 1, "kind": "custom", "scene_id": scene_id,
        "xml": str(xml), "xml_sha256": hashlib.sha256(xml.read_bytes()).hexdigest(),
        "n_frames": n_frames, "redraws": [], "materials": [], "emitters": [], "shapes": shapes,
        "camera": {"fov_x_deg": fov, "path": camera["path"], "frames": camera_path(
            camera["path"], origin, target, up / np.linalg.norm(up), n_frames, diagonal)},
        "animation": {"animated_light": None, "moving_shapes": [], "camera_cut_frame": None},
        "shapes_without_material_features": without,
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return manifest


def _material_record(bsdf) -> dict:
    """Roughness / metallic / transmissive of an XML BSDF, read from its class and parameters."""
    import mitsuba as mi

    if bsdf is None:
        return {"type": "diffuse", "roughness": 1.0}
    name = bsdf.class_name().lower()
    params = mi.traverse(bsdf)
    alpha = next((float(np.asarray(params[k]).ravel()[0]) for k in params.keys()
                  if k.split(".")[0] in ("alpha", "roughness", "alpha_u")), None)
    metallic_keys = [k for k in params.keys() if k.split(".")[0] == "metallic"]
    metallic = "conductor" in name or (bool(metallic_keys)
                                       and float(np.asarray(params[metallic_keys[0]]).ravel()[0]) > 0.5)
    if "principled" in name and alpha is not None:
        alpha = alpha ** 2  # principled "roughness" -> microfacet alpha
    kind = {"conductor": "conductor", "roughconductor": "roughconductor", "dielectric": "dielectric",
            "thindielectric": "thindielectric", "roughdielectric": "roughdielectric"}.get(name, name)
    smooth = kind in ("conductor", "dielectric", "thindielectric")
    return {"type": kind, "roughness": 0.0 if smooth else (1.0 if alpha is None else alpha),
            "metallic": metallic, "transmissive": "dielectric" in name}


def load_custom_frame_scene(manifest: dict, frame: int, *, width: int, height: int, integrator: dict,
                            sampler: dict | None = None):
    """The XML scene's shapes and emitters with the project's integrator and ``frame``'s sensor."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import attach_face_attributes, sensor_dict

    xml = Path(manifest["xml"])
    scene = _load_xml(xml)
    if hashlib.sha256(xml.read_bytes()).hexdigest() != manifest["xml_sha256"]:
        raise CustomSceneError(f"{xml} changed since the scene was imported; re-run generate_scene")
    scene_dict = {"type": "scene", "integrator": integrator,
                  "sensor": sensor_dict(manifest, frame, width=width, height=height, sampler=sampler)}
    for index, shape in enumerate(scene.shapes()):
        if isinstance(shape, mi.Mesh) and not shape.has_attribute("face_ident"):
            attach_face_attributes(shape, {"index": index}, _material_record(shape.bsdf()))
        scene_dict[f"shape_{index:03d}"] = shape
    for index, emitter in enumerate(scene.emitters()):
        if emitter.get_shape() is None:  # area emitters come with their shapes
            scene_dict[f"emitter_{index:03d}"] = emitter
    return mi.load_dict(scene_dict)
