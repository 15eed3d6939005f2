"""Manifest -> Mitsuba 3 scene dict for one frame, and the matching numpy camera projection.

`camera_matrices`, `project_to_pixels` and `object_to_world` are pure numpy (no Mitsuba variant
needed); `build_scene_dict` imports mitsuba lazily and expects a variant to be set
(`scenegen.mitsuba_env.init_mitsuba()`). `attach_face_attributes` writes the per-face material
attributes the feature integrator reads onto a loaded mesh (procedural and custom scenes alike).
"""
from __future__ import annotations

import copy
import pathlib
from typing import Any

import numpy as np

from scenegen.camera import camera_to_pixel_matrix, look_at_matrix

DEFAULT_INTEGRATOR = {"type": "path", "max_depth": 8}
DEFAULT_SAMPLER = {"type": "independent", "sample_count": 1}
SPECULAR_LIKE_ROUGHNESS = 0.1  # Isik et al. 2021, Sec. 3.1: alpha below this is treated as specular


# ---------------------------------------------------------------------------------------------
# Pure numpy
# ---------------------------------------------------------------------------------------------

def _frame_camera(manifest: dict, frame: int) -> dict:
    frames = manifest["camera"]["frames"]
    if not 0 <= frame < len(frames):
        raise IndexError(f"frame {frame} outside clip of {len(frames)} frames")
    return frames[frame]


def camera_matrices(manifest: dict, frame: int, width: int, height: int) -> dict:
    """Camera of `frame` as numpy matrices.

    Returns {'to_world': (4, 4) camera-to-world (Mitsuba look_at: +z forward, +y up, +x = image left),
    'world_to_camera': (4, 4), 'fov_x_deg', 'fov_y_deg', 'origin', 'target', 'up' (3,),
    'intrinsics': (3, 3) K with [u w, v w, w] = K @ p_camera (u, v in pixels, x right, y down, w = depth),
    'world_to_pixel': (3, 4) = K @ world_to_camera[:3],
    'world_to_ndc': (3, 4) like world_to_pixel but u / W, v / H, i.e. Mitsuba film coordinates in [0, 1]^2},
    plus 'width', 'height'.
    """
    cam = _frame_camera(manifest, frame)
    fov_x = float(cam["fov_x_deg"] if "fov_x_deg" in cam else manifest["camera"]["fov_x_deg"])
    origin, target, up = (np.asarray(cam[k], dtype=np.float64) for k in ("origin", "target", "up"))
    to_world = look_at_matrix(origin, target, up)
    world_to_camera = np.linalg.inv(to_world)
    intrinsics = camera_to_pixel_matrix(fov_x, width, height)
    world_to_pixel = intrinsics @ world_to_camera[:3]
    fov_y = float(np.degrees(2 * np.arctan(np.tan(np.radians(fov_x) / 2) * height / width)))
    return {
        "to_world": to_world, "world_to_camera": world_to_camera, "fov_x_deg": fov_x, "fov_y_deg": fov_y,
        "origin": origin, "target": target, "up": up, "intrinsics": intrinsics,
        "world_to_pixel": world_to_pixel,
        "world_to_ndc": np.diag([1.0 / width, 1.0 / height, 1.0]) @ world_to_pixel,
        "width": int(width), "height": int(height),
    }


def project_to_pixels(points_world: np.ndarray, manifest: dict, frame: int, width: int,
                      height: int) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) world points into `frame`'s image.

    Returns ((N, 2) continuous pixel coords (x right, y down; pixel (i, j) has its centre at
    (i + 0.5, j + 0.5), the visible image is [0, W) x [0, H)), (N,) bool: point is in front of the
    camera). Coordinates of points behind the camera are meaningless (NaN when exactly on the
    camera plane).
    """
    points = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    world_to_pixel = camera_matrices(manifest, frame, width, height)["world_to_pixel"]
    homogeneous = points @ world_to_pixel[:, :3].T + world_to_pixel[:, 3]
    depth = homogeneous[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = homogeneous[:, :2] / depth[:, None]
    return pixels, depth > 0.0


def object_to_world(manifest: dict, frame: int) -> np.ndarray:
    """(n_shapes, 4, 4) to_world of every shape at `frame` (row = the shape's `index`)."""
    out = np.empty((len(manifest["shapes"]), 4, 4))
    for shape in manifest["shapes"]:
        per_frame = shape.get("to_world_per_frame")
        out[shape["index"]] = per_frame[frame] if per_frame is not None else shape["to_world"]
    return out


def emitter_position(emitter: dict, frame: int) -> np.ndarray | None:
    """(3,) position of a point / spot emitter at `frame` (None for emitters without a position)."""
    if "position_per_frame" in emitter:
        return np.asarray(emitter["position_per_frame"][frame], dtype=np.float64)
    if "position" in emitter:
        return np.asarray(emitter["position"], dtype=np.float64)
    return None


def emitter_intensity(emitter: dict, frame: int) -> np.ndarray | None:
    """(3,) linear RGB intensity of a point / spot emitter at `frame`: ``intensity_per_frame[frame]`` when
    the emitter switches (stability scenario light_switch), else ``intensity``; None for other emitters."""
    if "intensity_per_frame" in emitter:
        return np.asarray(emitter["intensity_per_frame"][frame], dtype=np.float64)
    if "intensity" in emitter:
        return np.asarray(emitter["intensity"], dtype=np.float64)
    return None


# ---------------------------------------------------------------------------------------------
# Mitsuba dict
# ---------------------------------------------------------------------------------------------

def _resolve_params(params: Any, scene_dir: pathlib.Path, mi: Any) -> Any:
    """Copy of manifest material params with bitmap filenames made absolute and `to_uv` lists turned
    into mi.ScalarTransform4f."""
    if isinstance(params, dict):
        out = {k: _resolve_params(v, scene_dir, mi) for k, v in params.items()}
        if out.get("type") == "bitmap":
            out["filename"] = str((scene_dir / params["filename"]).resolve())
        if isinstance(params.get("to_uv"), list):
            out["to_uv"] = mi.ScalarTransform4f(np.asarray(params["to_uv"], dtype=np.float64))
        return out
    if isinstance(params, list):
        return [_resolve_params(v, scene_dir, mi) for v in params]
    return copy.deepcopy(params)


def _rgb(value: list[float]) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _spot_up(direction: np.ndarray) -> list[float]:
    """An up vector not parallel to the spot direction (look_at needs one)."""
    return [0.0, 0.0, 1.0] if abs(direction[1]) > 0.99 * np.linalg.norm(direction) else [0.0, 1.0, 0.0]


def sensor_dict(manifest: dict, frame: int, *, width: int, height: int, sampler: dict | None = None) -> dict:
    """Pinhole sensor of `frame` (box-filtered HDR film) as a Mitsuba dict."""
    import mitsuba as mi

    cam = _frame_camera(manifest, frame)
    return {
        "type": "perspective",
        "fov": float(cam.get("fov_x_deg", manifest["camera"]["fov_x_deg"])),
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=cam["origin"], target=cam["target"], up=cam["up"]),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": copy.deepcopy(sampler) if sampler is not None else dict(DEFAULT_SAMPLER),
    }


def build_scene_dict(manifest: dict, scene_dir: pathlib.Path, frame: int, *, width: int, height: int,
                     integrator: dict | None = None, sampler: dict | None = None) -> dict:
    """Plain Mitsuba scene dict for one frame (camera, object transforms, light positions of that frame).

    Shapes are keyed `shape_{index:03d}`, non-area emitters `emitter_{name}`. Note: `mi.load_dict` with
    its default `optimize=True` merges meshes whose BSDF dicts are identical into one shape (rendering is
    unchanged); load with `optimize=False`, or load each shape first, when per-shape identity matters.
    """
    import mitsuba as mi

    scene_dir = pathlib.Path(scene_dir)
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": copy.deepcopy(integrator) if integrator is not None else dict(DEFAULT_INTEGRATOR),
        "sensor": sensor_dict(manifest, frame, width=width, height=height, sampler=sampler),
    }
    to_worlds = object_to_world(manifest, frame)
    materials = manifest["materials"]
    for shape in manifest["shapes"]:
        index = shape["index"]
        entry: dict[str, Any] = {
            "type": "ply",
            "filename": str((scene_dir / shape["mesh"]).resolve()),
            "to_world": mi.ScalarTransform4f(to_worlds[index]),
            # The PLYs carry explicit (crease-aware) vertex normals; flat meshes carry face normals.
            "face_normals": False,
            "bsdf": _resolve_params(materials[shape["material"]]["params"], scene_dir, mi),
        }
        if shape.get("emitter") is not None:
            entry["emitter"] = {"type": "area", "radiance": _rgb(shape["emitter"]["radiance"])}
        scene[f"shape_{index:03d}"] = entry

    for emitter in manifest["emitters"]:
        key = f"emitter_{emitter['name']}"
        intensity = emitter_intensity(emitter, frame)
        if intensity is not None and not np.any(intensity > 0.0):
            continue   # switched off in this frame (intensity_per_frame)
        if emitter["type"] == "point":
            scene[key] = {"type": "point", "position": emitter_position(emitter, frame).tolist(),
                          "intensity": _rgb(intensity)}
        elif emitter["type"] == "spot":
            position = emitter_position(emitter, frame)
            target = np.asarray(emitter["target_per_frame"][frame] if "target_per_frame" in emitter
                                else emitter["target"], dtype=np.float64)
            scene[key] = {"type": "spot", "intensity": _rgb(intensity),
                          "cutoff_angle": float(emitter["cutoff_angle"]),
                          "beam_width": float(emitter.get("beam_width", 0.75 * emitter["cutoff_angle"])),
                          "to_world": mi.ScalarTransform4f().look_at(
                              origin=position.tolist(), target=target.tolist(), up=_spot_up(target - position))}
        elif emitter["type"] == "constant":
            scene[key] = {"type": "constant", "radiance": _rgb(emitter["radiance"])}
        elif emitter["type"] == "envmap":
            # Latitude-longitude map in the scene directory (open scenes' sky), +y up.
            scene[key] = {"type": "envmap", "filename": str((scene_dir / emitter["filename"]).resolve()),
                          "scale": float(emitter.get("scale", 1.0))}
        else:
            raise ValueError(f"unknown emitter type {emitter['type']!r}")
    return scene


# ---------------------------------------------------------------------------------------------
# Per-face attributes of loaded meshes
# ---------------------------------------------------------------------------------------------

def _material_is_specular_like(material: dict) -> bool:
    """Smooth Dirac materials, or non-diffuse materials rougher than nothing but below 0.1 alpha."""
    if material["type"] in ("conductor", "dielectric", "thindielectric"):
        return True
    if material["type"] in ("roughconductor", "roughdielectric"):
        return float(material.get("roughness", 1.0)) < SPECULAR_LIKE_ROUGHNESS
    return False


_CONDUCTOR_CLASSES = ("SmoothConductor", "RoughConductor")
_DIELECTRIC_CLASSES = ("SmoothDielectric", "RoughDielectric", "ThinDielectric")
# BSDFs with a diffuse lobe whose eval_diffuse_reflectance is Mitsuba's view-dependent default
# (pi x BSDF value towards the normal): their albedo is the directional albedo at normal incidence.
_QUADRATURE_CLASSES = ("BlendBSDF",)


def _uniform_rgb(params, name: str, default: float) -> np.ndarray | None:
    """(3,) value of the BSDF parameter ``name`` if it is a constant (or absent: ``default``); None if
    it is a texture."""
    key = f"{name}.value"
    if key in params:
        return np.broadcast_to(np.asarray(params[key], np.float64).ravel(), (3,)).copy()
    if any(k.startswith(f"{name}.") for k in params.keys()):
        return None
    return np.full(3, default)


def specular_albedo(bsdf) -> np.ndarray | None:
    """Feature albedo (3,) in [0, 1] of a conductor or dielectric ``mi.BSDF``, from its parameters.

    Conductors: ``specular_reflectance`` x normal-incidence Fresnel reflectance
    ((eta-1)^2 + k^2) / ((eta+1)^2 + k^2); dielectrics: ``specular_transmittance``. None for other
    BSDF classes and for textured parameters (the integrator then decides per sample)."""
    if bsdf is None:
        return None
    name = bsdf.class_name()
    if name not in _CONDUCTOR_CLASSES + _DIELECTRIC_CLASSES:
        return None
    import mitsuba as mi

    params = mi.traverse(bsdf)
    if name in _DIELECTRIC_CLASSES:
        tint = _uniform_rgb(params, "specular_transmittance", 1.0)
        return None if tint is None else np.clip(tint, 0.0, 1.0)
    eta, k = _uniform_rgb(params, "eta", np.nan), _uniform_rgb(params, "k", np.nan)
    tint = _uniform_rgb(params, "specular_reflectance", 1.0)
    if eta is None or k is None or tint is None or not np.all(np.isfinite(eta) & np.isfinite(k)):
        return None
    fresnel = ((eta - 1.0) ** 2 + k**2) / ((eta + 1.0) ** 2 + k**2)
    return np.clip(tint * fresnel, 0.0, 1.0)


def attach_face_attributes(mesh, shape: dict, material: dict | None) -> None:
    """Store (roughness, metallic, transmissive), (shape index, specular-like, albedo source) and the
    albedo colour per face of ``mesh`` (a loaded ``mi.Mesh``): the ``face_material`` / ``face_ident`` /
    ``face_albedo`` attributes ``scenegen.integrator`` reads.

    ``shape`` needs its ``index``; ``material`` is a manifest material record (None: diffuse, roughness 1).
    The albedo colour of conductors and dielectrics comes from the mesh's BSDF (``specular_albedo``);
    blend BSDFs get albedo source 2 (quadrature), others 0 (the integrator decides per sample).
    Used for procedural scenes (``scenegen.render``) and XML meshes (``scenegen.custom.scene``)."""
    import mitsuba as mi

    from scenegen.integrator import ALBEDO_SOURCE_ATTRIBUTE, ALBEDO_SOURCE_QUADRATURE

    n_faces = mesh.face_count()
    bsdf = mesh.bsdf()
    albedo = specular_albedo(bsdf)
    if albedo is not None:
        albedo_source = ALBEDO_SOURCE_ATTRIBUTE
    else:
        quadrature = bsdf is not None and bsdf.class_name() in _QUADRATURE_CLASSES
        albedo_source = ALBEDO_SOURCE_QUADRATURE if quadrature else 0.0
    albedo_row = (albedo if albedo is not None else np.zeros(3)).astype(np.float32)
    if material is None:
        mat_row = np.array([1.0, 0.0, 0.0], np.float32)
        ident_row = np.array([float(shape["index"]), 0.0, albedo_source], np.float32)
    else:
        mat_row = np.array([float(material.get("roughness", 1.0)), float(bool(material.get("metallic"))),
                            float(bool(material.get("transmissive")))], np.float32)
        ident_row = np.array([float(shape["index"]), float(_material_is_specular_like(material)),
                              albedo_source], np.float32)
    mesh.add_attribute("face_material", 3, mi.Float(np.tile(mat_row, n_faces)))
    mesh.add_attribute("face_ident", 3, mi.Float(np.tile(ident_row, n_faces)))
    mesh.add_attribute("face_albedo", 3, mi.Float(np.tile(albedo_row, n_faces)))


def preview_mean_luminance(manifest: dict, scene_dir: pathlib.Path, *, frame: int = 0, width: int = 32,
                           height: int = 32, spp: int = 4, max_depth: int = 6, seed: int = 0) -> float:
    """Render a tiny preview of `frame` and return its mean Rec.709 luminance (usable as luminance_check).

    Loaded with `optimize=False`: Mitsuba merges meshes that share a BSDF in a varying order, which
    changes the emitter/shape order and so the preview's noise realisation from load to load -- and
    with it whether a scene near the luminance bounds is accepted or redrawn.
    """
    import mitsuba as mi

    scene = mi.load_dict(build_scene_dict(
        manifest, scene_dir, frame, width=width, height=height,
        integrator={"type": "path", "max_depth": max_depth},
        sampler={"type": "independent", "sample_count": spp}), optimize=False)
    image = np.asarray(mi.render(scene, seed=seed), dtype=np.float64)[..., :3]
    return float((image @ np.array([0.2126, 0.7152, 0.0722])).mean())
