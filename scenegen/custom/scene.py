"""Bring-your-own scenes: a Mitsuba 3 XML file plus a camera path from the config.

``import_custom_scene`` writes a manifest in the procedural scenes' format (``"kind": "custom"``)
holding the XML's path and hash, one static entry per authored shape and the per-frame camera, so
the render, motion-vector and evaluation code treat custom scenes like generated ones.
``load_custom_frame_scene`` loads the XML, keeps its shapes and emitters, and swaps in the
project's integrator and the frame's sensor.

Rendered as authored where the per-sample design allows it (``scenegen.custom.parse`` reads what the
XML asks for): the integrator's ``max_depth``, ``rr_depth`` (unless the extra_scenes entry sets
them) and ``hide_emitters`` are honoured; the integrator itself, a pixel filter other than a
one-pixel box, the resolution, the sampler and a non-pinhole sensor are replaced, and every such
replacement is listed in ``manifest["substitutions"]`` ({what, authored, used, why}).

Shape identity: the XML is parsed with Mitsuba's mesh merging off, and ``merge`` shapes are
replaced by their children, so every authored shape stays a shape of its own. Every shape gets the
per-face attributes the feature integrator reads (``scenegen.mitsuba_scene.attach_face_attributes``:
shape index, material features, albedo source): meshes as mesh attributes, analytic shapes
(sphere, disk, cylinder, ...) as constant texture attributes with the same values. Instancing
(``shapegroup`` / ``instance``) and participating media are refused when the config is read
(``scenegen.custom.check``): they would not render as authored. The manifest records each shape's
material and area emitter, the other emitters, the ``$name`` params and the files the scene is made of.

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenegen.custom.parse import (
    CustomSceneError,
    ParsedXml,
    authored_settings,
    parse_xml,
    render_settings,
    substitutions,
)

IDENTITY = np.eye(4).tolist()
#: Mitsuba stores ``max_depth = -1`` ("no limit") as this unsigned 32-bit value; the feature integrator
#: counts depth in the same UInt32, so passing it reproduces Mitsuba's unlimited depth exactly.
UNBOUNDED_DEPTH = 2**32 - 1
log = logging.getLogger("scenegen")

__all__ = ["CustomSceneError", "LoadedXml", "camera_path", "import_custom_scene", "integrator_settings",
           "load_custom_frame_scene", "load_xml"]


@dataclass
class LoadedXml:
    """An XML scene ready to render: ``scene`` (every authored shape with its face attributes),
    ``shapes`` (manifest records in authored order), ``authored`` (parse.authored_settings), the
    ``materials`` the shapes index, the ``emitters`` that are not area lights ({name, type}) and the
    ``files`` the scene is made of ({path: SHA-256}, check.scene_files)."""

    scene: object
    shapes: list[dict]
    authored: dict
    materials: list[dict]
    emitters: list[dict]
    files: dict[str, str]


_scene_cache: dict[tuple[str, str], LoadedXml] = {}   # (resolved path, digest of its files and params) -> scene


def _material_record(bsdf) -> dict:
    """Roughness / metallic / transmissive of an XML BSDF, read from its class and parameters."""
    import mitsuba as mi

    if bsdf is None:
        return {"type": "diffuse", "roughness": 1.0}
    name = bsdf.class_name().lower()
    params = mi.traverse(bsdf)
    # Parameter name -> value, with a two-sided wrapper's "brdf_0." prefix dropped (its parameters are
    # those of the one-sided BSDF it wraps, whose class is not exposed: recognised by its parameters).
    values = {key.removeprefix("brdf_0.").split(".")[0]: params[key] for key in params.keys()}
    if name.startswith("twosided"):
        if {"eta", "k"} <= set(values):
            name = "roughconductor" if {"alpha", "alpha_u"} & set(values) else "smoothconductor"
        elif "diffuse_reflectance" in values:
            name = "roughplastic" if "alpha" in values else "smoothplastic"
        elif "reflectance" in values:
            name = "smoothdiffuse"
    alpha = next((float(np.asarray(values[k]).ravel()[0]) for k in ("alpha", "roughness", "alpha_u")
                  if k in values), None)
    metallic = "conductor" in name or ("metallic" in values and float(np.asarray(values["metallic"]).ravel()[0]) > 0.5)
    if "principled" in name and alpha is not None:
        alpha = alpha ** 2  # principled "roughness" -> microfacet alpha
    # Mitsuba's class names (SmoothConductor, RoughDielectric, ...) -> the plugin names of the manifest.
    kind = {"smoothconductor": "conductor", "roughconductor": "roughconductor", "smoothdielectric": "dielectric",
            "thindielectric": "thindielectric", "roughdielectric": "roughdielectric", "smoothdiffuse": "diffuse",
            "smoothplastic": "plastic"}.get(name, name)
    smooth = kind in ("conductor", "dielectric", "thindielectric")
    return {"type": kind, "roughness": 0.0 if smooth else (1.0 if alpha is None else alpha),
            "metallic": metallic, "transmissive": "dielectric" in name}


def _attribute_rows(bsdf, index: int, material: dict) -> dict[str, list[float]]:
    """The constant per-face rows attach_face_attributes writes for a shape with ``bsdf`` and ``index``:
    {attribute name: 3 floats}, read back from a one-triangle probe mesh (one source of truth)."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import attach_face_attributes

    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    probe = mi.Mesh("attribute_probe", 3, 1, props)
    attach_face_attributes(probe, {"index": index}, material)
    rows = {}
    for name in ("face_material", "face_ident", "face_albedo"):
        if bool(probe.has_attribute(name)[0]):
            rows[name] = [float(v) for v in np.asarray(probe.attribute_buffer(name))[:3]]
    return rows


def _emitter_record(emitter) -> dict | None:
    """The manifest record of a shape's area emitter (None without one): its type and, for a constant
    radiance, the RGB value; a textured radiance is named by its texture class."""
    import mitsuba as mi

    if emitter is None:
        return None
    params = mi.traverse(emitter)
    record: dict = {"type": "area"}
    if "radiance.value" in params.keys():
        record["radiance"] = [round(float(v), 6) for v in np.asarray(params["radiance.value"]).ravel()[:3]]
    else:
        # The texture's class (BitmapTexture, ...): SceneParameters.properties holds (value, type, node, flags).
        nodes = [params.properties[key][2] for key in params.keys() if key.startswith("radiance.")]
        name = nodes[0].class_name() if nodes else "texture"
        record["radiance_texture"] = "bitmap" if name.startswith("BitmapTexture") else name.lower()
    return record


def load_xml(xml: Path, params: dict | None = None) -> LoadedXml:
    """Load ``xml`` with the ``$name`` ``params`` once per process (see the module docstring); CustomSceneError
    naming the file. ``shapes`` records each authored shape's material (an index into ``materials``, None
    inside a shape group) and area emitter."""
    import mitsuba as mi

    from scenegen.custom.check import scene_files

    path = Path(xml).resolve()
    if not path.is_file():
        raise CustomSceneError(f"custom scene XML not found: {path}")
    files = scene_files({"name": path.stem, "xml": str(path), "params": params})
    key = (str(path), hashlib.sha256(json.dumps([files, params or {}], sort_keys=True, default=str)
                                     .encode()).hexdigest())
    if key in _scene_cache:
        return _scene_cache[key]
    # Pass 1 instantiates the XML as authored (separate shapes) to read each shape's BSDF; pass 2
    # re-parses it with constant texture attributes on the analytic shapes (they take attributes only
    # at construction), then meshes get theirs as mesh attributes.
    first: ParsedXml = parse_xml(path, params)
    scene = first.instantiate()
    by_id = {shape.id(): shape for shape in scene.shapes()}
    second = parse_xml(path, params)
    shapes, materials, records = [], {}, []
    for index, (node_id, name, plugin) in enumerate(first.shapes):
        shape = by_id.get(node_id)
        material = _material_record(shape.bsdf()) if shape is not None else None
        is_mesh = isinstance(shape, mi.Mesh)
        if shape is not None and not is_mesh:
            second.set_texture_attributes(index, _attribute_rows(shape.bsdf(), index, material))
        materials[node_id] = material
        if material is not None:
            bsdf_id = shape.bsdf().id()
            records.append({"name": bsdf_id if bsdf_id and not bsdf_id.startswith("_unnamed") else f"{name}.bsdf",
                            **material})
        shapes.append({"index": index, "name": name, "type": plugin, "kind": "custom", "mesh": None,
                       "material": len(records) - 1 if material is not None else None,
                       "emitter": _emitter_record(shape.emitter()) if shape is not None else None,
                       "to_world": IDENTITY, "to_world_per_frame": None, "material_features": shape is not None})
    final = second.instantiate()
    from scenegen.mitsuba_scene import attach_face_attributes

    index_of = {node_id: index for index, (node_id, _, _) in enumerate(second.shapes)}
    for shape in final.shapes():
        if isinstance(shape, mi.Mesh) and shape.id() in index_of:
            attach_face_attributes(shape, {"index": index_of[shape.id()]}, materials[shape.id()])
    emitters = [{"name": emitter.id() or f"emitter_{index:03d}", "type": _emitter_plugin(emitter)}
                for index, emitter in enumerate(e for e in scene.emitters() if e.get_shape() is None)]
    loaded = LoadedXml(final, shapes, authored_settings(first, scene), records, emitters, files)
    _scene_cache[key] = loaded
    return loaded


def _emitter_plugin(emitter) -> str:
    """Plugin name of a loaded emitter from its class (PointLight -> point, EnvironmentMapEmitter -> envmap)."""
    name = emitter.class_name()
    known = {"PointLight": "point", "SpotLight": "spot", "DirectionalEmitter": "directional",
             "EnvironmentMapEmitter": "envmap", "ConstantBackgroundEmitter": "constant",
             "AreaLight": "area", "ProjectiveLight": "projector", "SunSkyEmitter": "sunsky"}
    return known.get(name, name.lower())


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
    loaded = load_xml(xml, entry.get("params"))
    scene = loaded.scene
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
    without = [shape["name"] for shape in loaded.shapes if not shape["material_features"]]
    if without:
        log.warning("custom scene %s: %d shapes inside shape groups without material features: %s", scene_id,
                    len(without), ", ".join(without))
    manifest = {
        "format_version": 1, "kind": "custom", "scene_id": scene_id,
        "xml": str(xml), "xml_sha256": hashlib.sha256(xml.read_bytes()).hexdigest(),
        "params": dict(entry.get("params") or {}), "files": loaded.files,
        "n_frames": n_frames, "redraws": [], "materials": loaded.materials, "emitters": loaded.emitters,
        "shapes": loaded.shapes,
        "camera": {"fov_x_deg": fov, "path": camera["path"], "frames": camera_path(
            camera["path"], origin, target, up / np.linalg.norm(up), n_frames, diagonal)},
        "animation": {"animated_light": None, "moving_shapes": [], "camera_cut_frame": None},
        "shapes_without_material_features": without,
        "authored": loaded.authored,
        "render": render_settings(loaded.authored, entry),
        "substitutions": substitutions(loaded.authored, entry),
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return manifest


def integrator_settings(manifest: dict) -> dict:
    """Integrator properties the manifest fixes (max_depth, rr_depth, hide_emitters); {} for manifests
    written before they were recorded. ``max_depth`` -1 (no limit) becomes UNBOUNDED_DEPTH."""
    render = manifest.get("render")
    if not render:
        return {}
    depth = int(render["max_depth"])
    return {"max_depth": UNBOUNDED_DEPTH if depth < 0 else depth, "rr_depth": int(render["rr_depth"]),
            "hide_emitters": bool(render["hide_emitters"])}


def load_custom_frame_scene(manifest: dict, frame: int, *, width: int, height: int, integrator: dict,
                            sampler: dict | None = None):
    """The XML scene's shapes and emitters with the project's integrator (``integrator`` with the
    manifest's integrator_settings) and ``frame``'s sensor (box filter, ``width`` x ``height``)."""
    import mitsuba as mi

    from scenegen.mitsuba_scene import sensor_dict

    xml = Path(manifest["xml"])
    if not xml.is_file():
        raise CustomSceneError(f"custom scene XML not found: {xml}")
    if hashlib.sha256(xml.read_bytes()).hexdigest() != manifest["xml_sha256"]:
        raise CustomSceneError(f"{xml} changed since the scene was imported; re-run generate_scene")
    loaded = load_xml(xml, manifest.get("params"))
    if "files" in manifest and loaded.files != manifest["files"]:
        changed = sorted(set(loaded.files.items()) ^ set(manifest["files"].items()))
        raise CustomSceneError(f"the files of {xml} changed since the scene was imported "
                               f"({', '.join(sorted({name for name, _ in changed}))}); re-run generate_scene")
    scene = loaded.scene
    settings = {**integrator, **integrator_settings(manifest)}
    if settings["type"] == "path" and settings.get("max_depth") == UNBOUNDED_DEPTH:
        settings["max_depth"] = -1   # Mitsuba's own integrators take a signed int: -1 is "no limit"
    scene_dict = {"type": "scene", "integrator": settings,
                  "sensor": sensor_dict(manifest, frame, width=width, height=height, sampler=sampler)}
    for index, shape in enumerate(scene.shapes()):
        scene_dict[f"shape_{index:03d}"] = shape
    for index, emitter in enumerate(scene.emitters()):
        if emitter.get_shape() is None:  # area emitters come with their shapes
            scene_dict[f"emitter_{index:03d}"] = emitter
    # optimize=False: Mitsuba would otherwise merge meshes with equal BSDFs (and their ids) into one.
    return mi.load_dict(scene_dict, optimize=False)
