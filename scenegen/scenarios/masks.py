"""Where and when a stability scenario's difficulty happens, derived from its renders (rule derive_masks).

Every mask is (T, H, W) bool and computed for every scenario (a scenario's ``focus`` names the ones its
phenomenon fills; the others mark whatever else the renderer saw, usually nothing). A frame has
*history* when it is not frame 0 and not a camera cut (the renderer's sidecar ``camera_cut``).

* ``disocclusion``: no valid reprojection (the renderer's ``motion.valid``) in a frame with history.
* ``shadow``: direct visibility of a light that is on in both frames changed between t - 1 and t at a
  pixel whose reprojection is valid: shadow rays (Mitsuba ``ray_test`` in the scene of each frame) from
  the pixel-centre G-buffer point, and from the same point moved with its shape to frame t - 1.
* ``indirect_only``: a surface pixel that no point, spot or area light (area lights: the emitter shape's
  centre) lights directly -- occluded, facing away or outside a spot's cone; environment light and
  switched-off lights do not count.
* ``specular``: at least half the pixel's samples see a mirror (first camera vertex specular, not
  refracted) or a glossy surface (roughness below GLOSSY_ROUGHNESS at the first non-specular vertex).
* ``transmission``: at least half the samples refracted through glass (``flags.transmissive``).
* ``firefly``: a sample's luminance exceeds FIREFLY_FRAME_RATIO x the frame's median reference luminance
  and FIREFLY_PIXEL_RATIO x the pixel's reference luminance.
* ``fast_motion``: motion vector length >= FAST_MOTION_FRACTION x the image width, in a frame with history.
* ``texture``: the reference albedo differs from its 3 x 3 mean by more than TEXTURE_CONTRAST where all
  nine pixels show the same shape (texture detail, not object edges).
* ``subject``: the pixel-centre G-buffer hits one of the scenario's subject shapes.

Outputs in ``out_dir``: ``masks/frame_TTTT.exr`` (channels ``mask.<kind>``, HALF 0/1) and ``events.json``
(events of the manifest and of the renders, per-frame pixel counts of every mask, the thresholds used).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scenegen.scenarios.registry import MASK_KINDS

GLOSSY_ROUGHNESS = 0.3
FIREFLY_FRAME_RATIO = 16.0
FIREFLY_PIXEL_RATIO = 4.0
FAST_MOTION_FRACTION = 0.15
TEXTURE_CONTRAST = 0.05
SHADOW_RAY_OFFSET_M = 1e-3
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)


def _luminance(rgb: np.ndarray, axis: int) -> np.ndarray:
    return np.tensordot(np.moveaxis(rgb, axis, -1), LUMINANCE, axes=1)


def _neighbourhood(image: np.ndarray) -> np.ndarray:
    """(9, ..., H, W): the 3 x 3 neighbours of every pixel of ``image`` (..., H, W), edges replicated."""
    pad = [(0, 0)] * (image.ndim - 2) + [(1, 1), (1, 1)]
    padded = np.pad(image, pad, mode="edge")
    h, w = image.shape[-2:]
    return np.stack([padded[..., dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])


def texture_mask(albedo: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(T, H, W) texture detail from reference albedo (T, 3, H, W) and G-buffer object ids (T, H, W)."""
    contrast = np.abs(albedo - _neighbourhood(albedo).mean(axis=0)).max(axis=1)
    same_shape = np.all(_neighbourhood(objects) == objects[None], axis=0) & (objects >= 0)
    return (contrast > TEXTURE_CONTRAST) & same_shape


def firefly_mask(samples: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(T, H, W) from per-sample radiance (T, S, 3, H, W) and reference radiance (T, 3, H, W)."""
    peak = _luminance(samples, axis=2).max(axis=1)
    ref = _luminance(reference, axis=1)
    frame = np.median(ref.reshape(ref.shape[0], -1), axis=1)[:, None, None]
    return (peak > FIREFLY_FRAME_RATIO * np.maximum(frame, 1e-6)) & (peak > FIREFLY_PIXEL_RATIO * ref)


def _lights(manifest: dict, frame: int) -> list[dict]:
    """Lights of ``frame`` that are on: {'name', 'position' (3,), optional 'axis' (3,) and 'cos_cutoff'}."""
    from scenegen.mitsuba_scene import emitter_intensity, emitter_position, object_to_world

    out = []
    for emitter in manifest["emitters"]:
        position = emitter_position(emitter, frame)
        intensity = emitter_intensity(emitter, frame)
        if position is None or (intensity is not None and not np.any(intensity > 0)):
            continue
        light = {"name": emitter["name"], "position": position}
        if emitter["type"] == "spot":
            target = np.asarray(emitter.get("target_per_frame", [emitter.get("target")] * (frame + 1))[frame])
            light["axis"] = (target - position) / np.linalg.norm(target - position)
            light["cos_cutoff"] = float(np.cos(np.radians(emitter["cutoff_angle"])))
        out.append(light)
    to_world = object_to_world(manifest, frame)
    for shape in manifest["shapes"]:
        if shape.get("emitter") is not None:
            out.append({"name": shape["name"], "position": to_world[shape["index"]][:3, 3]})
    return out


def _visible(scene, points: np.ndarray, normals: np.ndarray, light: dict) -> np.ndarray:
    """(N,) bool: ``light`` lights the (N, 3) surface points with (N, 3) normals directly in ``scene``."""
    import drjit as dr
    import mitsuba as mi

    to_light = light["position"][None] - points
    facing = np.sum(to_light * normals, axis=1) > 0.0
    origins = points + SHADOW_RAY_OFFSET_M * normals * np.where(facing, 1.0, -1.0)[:, None]
    delta = light["position"][None] - origins
    distance = np.linalg.norm(delta, axis=1)
    direction = delta / np.maximum(distance, 1e-12)[:, None]
    ray = mi.Ray3f(mi.Point3f(*(mi.Float(c) for c in origins.T.astype(np.float32))),
                   mi.Vector3f(*(mi.Float(c) for c in direction.T.astype(np.float32))))
    ray.maxt = mi.Float((distance * (1.0 - 1e-4)).astype(np.float32))
    occluded = scene.ray_test(ray)
    dr.eval(occluded)
    lit = facing & ~np.asarray(occluded, dtype=bool)
    if "axis" in light:
        lit &= np.sum(-direction * light["axis"][None], axis=1) >= light["cos_cutoff"]
    return lit


def _rigid_to_previous(manifest: dict, frame: int, objects: np.ndarray) -> np.ndarray:
    """(N, 4, 4) per-pixel rigid motion from frame t to t - 1 of the shape each pixel hits (identity on a miss)."""
    from scenegen.mitsuba_scene import object_to_world

    motion = np.einsum("kij,kjl->kil", object_to_world(manifest, frame - 1),
                       np.linalg.inv(object_to_world(manifest, frame)))
    out = np.tile(np.eye(4), (objects.size, 1, 1))
    hit = objects >= 0
    out[hit] = motion[objects[hit]]
    return out


def visibility_masks(manifest: dict, scene_dir: Path, settings, gbuffer: dict[str, np.ndarray],
                     valid: np.ndarray, history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(shadow, indirect_only), each (T, H, W) bool, by shadow rays from the pixel-centre G-buffer
    (``gbuffer`` position/normal (T, 3, H, W), object (T, 1, H, W)); ``valid`` (T, H, W), ``history`` (T,)."""
    from scenegen.render import load_frame_scene

    n_frames, _, height, width = gbuffer["position"].shape
    shadow = np.zeros((n_frames, height, width), bool)
    indirect = np.zeros_like(shadow)
    previous_scene = None
    for t in range(n_frames):
        scene = load_frame_scene(manifest, scene_dir, t, settings)
        points = gbuffer["position"][t].reshape(3, -1).T.astype(np.float64)
        normals = gbuffer["normal"][t].reshape(3, -1).T.astype(np.float64)
        objects = np.rint(gbuffer["object"][t, 0]).astype(np.int64).reshape(-1)
        hit = objects >= 0
        lights = _lights(manifest, t)
        lit_now = {light["name"]: _visible(scene, points, normals, light) & hit for light in lights}
        lit_any = np.any(list(lit_now.values()), axis=0) if lit_now else np.zeros(hit.shape, bool)
        indirect[t] = (hit & ~lit_any).reshape(height, width)
        if history[t] and previous_scene is not None:
            rigid = _rigid_to_previous(manifest, t, objects)
            points_prev = np.einsum("nij,nj->ni", rigid[:, :3, :3], points) + rigid[:, :3, 3]
            normals_prev = np.einsum("nij,nj->ni", rigid[:, :3, :3], normals)
            changed = np.zeros(hit.shape, bool)
            for light in _lights(manifest, t - 1):
                if light["name"] in lit_now:   # on in both frames
                    changed |= lit_now[light["name"]] != (_visible(previous_scene, points_prev, normals_prev, light)
                                                          & hit)
            shadow[t] = changed.reshape(height, width) & valid[t]
        previous_scene = scene
    return shadow, indirect


def derive_masks(cfg: dict, scene_id: str, scene_dir: Path, render_dir: Path, out_dir: Path) -> dict:
    """Write ``out_dir``/masks/frame_TTTT.exr and events.json for stability scene ``scene_id``; return the events."""
    from scenegen.atomic import atomic_directory, write_text_atomic
    from scenegen.catalog import scene_render_config
    from scenegen.dataset import load_clip
    from scenegen.exr import write_exr
    from scenegen.mitsuba_env import init_mitsuba
    from scenegen.render import RenderSettings

    settings = RenderSettings.from_config(scene_render_config(cfg, scene_id))
    init_mitsuba(settings.variant)
    manifest = json.loads((Path(scene_dir) / "manifest.json").read_text())
    if "stability" not in manifest:
        raise ValueError(f"{scene_dir}: not a stability scenario (no 'stability' record in its manifest)")
    clip = load_clip(Path(render_dir), buffers=["radiance", "depth", "roughness", "flags"], reference=True)
    n_frames, _, height, width = clip.valid.shape
    cuts = np.array([bool(meta.get("camera_cut")) for meta in clip.meta])
    history = (np.arange(n_frames) > 0) & ~cuts
    valid = clip.valid[:, 0]
    objects = np.rint(clip.gbuffer["object"][:, 0]).astype(np.int64)
    flags = clip.samples["flags"] > 0.5                               # (T, S, 4, H, W)
    specular_bounce, transmissive = flags[:, :, 3], flags[:, :, 2]
    hit = clip.samples["depth"][:, :, 0] > 0
    glossy = hit & ~specular_bounce & (clip.samples["roughness"][:, :, 0] < GLOSSY_ROUGHNESS)
    speed = np.linalg.norm(clip.motion, axis=1)
    shadow, indirect = visibility_masks(manifest, Path(scene_dir), settings, clip.gbuffer, valid, history)
    masks = {
        "disocclusion": ~valid & history[:, None, None],
        "shadow": shadow,
        "specular": ((specular_bounce & ~transmissive).mean(axis=1) >= 0.5) | (glossy.mean(axis=1) >= 0.5),
        "transmission": transmissive.mean(axis=1) >= 0.5,
        "firefly": firefly_mask(clip.samples["radiance"], clip.reference["radiance"]),
        "indirect_only": indirect,
        "fast_motion": (speed >= FAST_MOTION_FRACTION * width) & history[:, None, None],
        "texture": texture_mask(clip.reference["albedo"], objects),
        "subject": np.isin(objects, manifest["stability"]["subject_shapes"]),
    }
    assert tuple(masks) == MASK_KINDS
    record = manifest["stability"]
    events = [dict(event, source="manifest") for event in record["events"]]
    events += [{"frame": int(t), "kind": "camera_cut", "source": "renderer"} for t in np.flatnonzero(cuts)]
    events += [{"frame": int(t), "kind": "fast_motion", "source": "renderer",
                "max_motion_px": round(float(speed[t].max()), 3)} for t in np.flatnonzero(masks["fast_motion"].any((1, 2)))]
    summary = {
        "scene": scene_id, "scenario": record["scenario"], "description": record["description"],
        "frames": int(n_frames), "width": int(width), "height": int(height), "focus": record["focus"],
        "subject_shapes": record["subject_shapes"],
        "events": sorted(events, key=lambda e: (e["frame"], e["kind"], e["source"])),
        "mask_pixels": {kind: [int(n) for n in mask.sum(axis=(1, 2))] for kind, mask in masks.items()},
        "thresholds": {"glossy_roughness": GLOSSY_ROUGHNESS, "firefly_frame_ratio": FIREFLY_FRAME_RATIO,
                       "firefly_pixel_ratio": FIREFLY_PIXEL_RATIO, "fast_motion_px": FAST_MOTION_FRACTION * width,
                       "texture_contrast": TEXTURE_CONTRAST},
        "masks": "masks/frame_TTTT.exr, channels mask.<kind>, HALF 0/1",
    }
    with atomic_directory(Path(out_dir)) as tmp_dir:
        (tmp_dir / "masks").mkdir()
        for t, meta in enumerate(clip.meta):
            write_exr(tmp_dir / "masks" / f"frame_{int(meta['frame']):04d}.exr",
                      {f"mask.{kind}": mask[t].astype(np.float32) for kind, mask in masks.items()},
                      half=lambda name: True)
        write_text_atomic(tmp_dir / "events.json", json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return summary
