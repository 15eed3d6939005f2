"""Seeded volumetric clips (Iglesias-Guitian et al. 2022): one heterogeneous medium in a box, lit by an
environment plus a point or small area light, seen by a camera orbiting it, in three scenario kinds that
each animate exactly one element while everything else stays fixed:

* ``'camera'``: the camera moves along an orbit around the volume; light and transfer function fixed;
* ``'light'``: the light orbits the volume; camera and transfer function fixed;
* ``'transfer_function'``: the transfer function is edited over time -- an opacity ramp sliding
  (``TransferFunction.shifted``) or a colour change (``interpolate`` towards ``recoloured``); camera and
  light fixed.

:func:`generate_volume_clip` draws everything from one seed (streams derived with ``scenegen.seeds``) and
returns a :class:`VolumeClip` built *from its own rounded manifest*, so the manifest describes the scene
completely: the field (kind, parameters, seed -- not the voxels: :func:`field_from_manifest` regenerates
the same bytes), the medium box, the transfer function of every frame, the environment, the light and the
camera of every frame. Same seed, same manifest bytes (floats rounded to ``FLOAT_DECIMALS``).

Settings: ``'open'`` (the environment -- a constant or a sky/ground gradient map built in memory -- and a
grey ground plane under the box) or ``'room'`` (a closed diffuse room around the volume; the environment is
then hidden and omitted from the scene). Only these scenes use the volumetric integrator
(``mcdn_volpath_features``); surface-only scenes keep the surface integrator of scenegen.mitsuba_scene.

Rendering a clip: either ``mi.load_dict(clip.scene_dict(t))`` per frame, or load frame 0 once and call
:func:`frame_updates` before each frame. It edits the loaded scene through ``mi.traverse``: the
medium grids (``update_medium``) for 'transfer_function', the ``sensor.to_world`` for 'camera', and the
light's ``light.position`` (point light) or ``light.to_world`` (area light on a rectangle) for 'light'.
Mitsuba functions need a variant set (``scenegen.mitsuba_env.init_mitsuba()``).
"""
from __future__ import annotations

import copy
import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scenegen.camera import look_at_matrix
from scenegen.generate import FLOAT_DECIMALS, _jsonable
from scenegen.seeds import derive_seed
from scenegen.volumes.fields import noise_cloud, smoke_plume
from scenegen.volumes.framing import UP, framing_distance, framing_spill, occupied_bounds, orbit_radius
from scenegen.volumes.media import TransferFunction

FORMAT_VERSION = 1
SCENARIOS = ("camera", "light", "transfer_function")
FIELD_KINDS = ("noise_cloud", "smoke_plume", "shells")
SHELL_PRIMITIVES = ("icosphere", "capsule", "torus")
SETTINGS = ("open", "room")
LIGHT_KINDS = ("point", "area")
TF_EDITS = ("slide", "recolour")
ENVIRONMENTS = ("constant", "gradient")
ROOM_SIZE_M = (6.0, 4.0, 6.0)
ROOM_CAMERA_DISTANCE = 2.6            # farthest the camera orbits from the volume inside the room
GRADIENT_MAP_SIZE = (16, 32)          # (height, width) of the latitude-longitude gradient map
MEDIUM_KEY = "volume"                 # scene-dict key of the medium box: traverse prefix 'volume.interior_medium'


def _r4(x: float) -> float:
    """Drawn constants on a 1e-4 grid: sums and shifts of them stay distinct after JSON rounding."""
    return round(float(x), 4)


def _rgb(rng: np.random.Generator, lo: Any, hi: Any) -> list[float]:
    """Three uniform draws in [lo, hi) (scalars or per-channel), on the 1e-4 grid."""
    return [_r4(v) for v in rng.uniform(lo, hi, 3)]


# ---------------------------------------------------------------------------------------------
# Fields
# ---------------------------------------------------------------------------------------------

def _shell_mesh(params: dict) -> Any:
    import trimesh

    primitive = params["primitive"]
    if primitive == "icosphere":
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    elif primitive == "capsule":
        mesh = trimesh.creation.capsule(height=params["height"], radius=1.0, count=[16, 16])
    elif primitive == "torus":
        mesh = trimesh.creation.torus(major_radius=1.0, minor_radius=params["minor_radius"],
                                      major_sections=24, minor_sections=12)
    else:
        raise ValueError(f"unknown shell primitive {primitive!r}; expected one of {SHELL_PRIMITIVES}")
    mesh.apply_scale(np.asarray(params["axis_scale"], dtype=np.float64))
    mesh.apply_transform(trimesh.transformations.euler_matrix(*params["rotation_rad"]))
    return mesh


NPY_KIND = "npy"


def _npy_values(path: Path) -> np.ndarray:
    """The (D, H, W) real, finite array of a .npy file; ValueError naming the file otherwise."""
    if not path.is_file():
        raise FileNotFoundError(f"volume field {path}: no such file")
    try:
        values = np.load(path, allow_pickle=False)
    except ValueError as error:
        raise ValueError(f"volume field {path}: not a readable .npy array ({error})") from error
    if values.ndim != 3 or min(values.shape) < 2:
        raise ValueError(f"volume field {path}: needs a 3-D (D, H, W) array with every side >= 2, got shape "
                         f"{values.shape}")
    if values.dtype.kind not in "fiu":
        raise ValueError(f"volume field {path}: needs real numbers, got dtype {values.dtype}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"volume field {path}: {int((~np.isfinite(values)).sum())} non-finite values")
    if values.max() <= values.min():
        raise ValueError(f"volume field {path}: constant ({values.min()}); a transfer function needs a range")
    return values


def npy_field_description(path: str | Path) -> dict:
    """Manifest 'field' entry of a user's .npy scalar field: its path, SHA-256, shape, dtype and value range; the
    field is its values mapped linearly from [min, max] to [0, 1] (float32). The voxels stay in the file; the
    digest makes a later render refuse a changed file."""
    path = Path(path)
    values = _npy_values(path)
    return {"kind": NPY_KIND, "path": str(path), "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "shape": [int(n) for n in values.shape], "dtype": str(values.dtype),
            "value_range": [float(values.min()), float(values.max())], "resolution": int(max(values.shape))}


def _npy_field(description: dict) -> np.ndarray:
    path = Path(description["path"])
    digest = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    if digest != description["sha256"]:
        raise ValueError(f"volume field {path}: its contents changed since the scene was generated (SHA-256 "
                         f"{digest} != {description['sha256']}); regenerate the scene")
    values = _npy_values(path).astype(np.float64)
    low, high = description["value_range"]
    return np.clip((values - low) / (high - low), 0.0, 1.0).astype(np.float32)


def field_from_description(description: dict) -> np.ndarray:
    """(D, H, W) float32 field in [0, 1] from a manifest 'field' entry (kind, resolution, seed, params; or a
    user's .npy file, kind 'npy')."""
    if description["kind"] == NPY_KIND:
        return _npy_field(description)
    kind, resolution, params = description["kind"], int(description["resolution"]), description["params"]
    if kind == "noise_cloud":
        return noise_cloud(np.random.default_rng(int(description["seed"])), resolution, **params)
    if kind == "smoke_plume":
        return smoke_plume(np.random.default_rng(int(description["seed"])), resolution, **params)
    if kind == "shells":
        from scenegen.volumes.mesh import shells_from_mesh

        return shells_from_mesh(_shell_mesh(params), resolution, int(params["layers"]))
    raise ValueError(f"unknown field kind {kind!r}; expected one of {FIELD_KINDS}")


def field_from_manifest(manifest: dict) -> np.ndarray:
    """The clip's scalar field, regenerated from ``manifest['field']`` (same bytes as ``clip.field``)."""
    return field_from_description(manifest["field"])


def _draw_field(rng: np.random.Generator, kind: str, seed: int, resolution: int) -> dict:
    if kind == "noise_cloud":
        params = {"octaves": int(rng.integers(3, 5)), "base_frequency": int(rng.integers(2, 5)),
                  "persistence": _r4(rng.uniform(0.4, 0.6)), "turbulence": _r4(rng.uniform(0.6, 1.1))}
    elif kind == "smoke_plume":
        params = {"base_radius": _r4(rng.uniform(0.04, 0.08)), "top_radius": _r4(rng.uniform(0.18, 0.3)),
                  "sway": _r4(rng.uniform(0.05, 0.15)), "turbulence": _r4(rng.uniform(0.4, 0.8))}
    elif kind == "shells":
        primitive = SHELL_PRIMITIVES[int(rng.integers(len(SHELL_PRIMITIVES)))]
        params = {"primitive": primitive, "layers": int(rng.integers(3, 5)),
                  "axis_scale": _rgb(rng, 0.75, 1.0),
                  "rotation_rad": [_r4(v) for v in rng.uniform(-math.pi, math.pi, 3)]}
        if primitive == "capsule":
            params["height"] = _r4(rng.uniform(0.6, 1.6))
        elif primitive == "torus":
            params["minor_radius"] = _r4(rng.uniform(0.35, 0.55))
    else:
        raise ValueError(f"unknown field kind {kind!r}; expected one of {FIELD_KINDS}")
    return {"kind": kind, "resolution": int(resolution), "seed": int(derive_seed(seed, "volume_field")),
            "params": params}


def _draw_transfer_function(rng: np.random.Generator, field: dict) -> TransferFunction:
    """Clouds and plumes: a linear opacity ramp above a low threshold, near-white tinted albedo. Shells with L
    layers (plateaus 1/L, ..., 1): a translucent pinkish 'skin' from 1/L, a dense whitish 'bone' at 1."""
    if field["kind"] == "shells":
        layers = int(field["params"]["layers"])
        skin, bone = _r4(rng.uniform(0.8, 2.5)), _r4(rng.uniform(15.0, 35.0))
        a, b, c, d = (_r4(v / layers) for v in (0.5, 1.0, layers - 1.0, layers - 0.5))
        skin_rgb = _rgb(rng, [0.8, 0.45, 0.35], [0.95, 0.65, 0.5])
        bone_rgb = _rgb(rng, [0.85, 0.82, 0.7], [0.95, 0.92, 0.85])
        return TransferFunction([(0.0, 0.0), (a, 0.0), (b, skin), (c, skin), (d, bone), (1.0, bone)],
                                [(0.0, *skin_rgb), (b, *skin_rgb), (c, *skin_rgb), (d, *bone_rgb), (1.0, *bone_rgb)])
    lo = _r4(rng.uniform(0.05, 0.2))
    hi = _r4(rng.uniform(0.55, 0.9))
    sigma = _r4(rng.uniform(4.0, 12.0))
    thin_rgb, dense_rgb = _rgb(rng, 0.75, 0.95), _rgb(rng, 0.6, 0.95)
    return TransferFunction([(0.0, 0.0), (lo, 0.0), (hi, sigma), (1.0, sigma)],
                            [(0.0, *thin_rgb), (1.0, *dense_rgb)])


def _rounded(tf: TransferFunction) -> TransferFunction:
    """``tf`` with its control points rounded as in the manifest, dropping knots that rounding merges
    (a shift can leave a knot at 1 - 1e-16 next to the end knot 1)."""
    def clean(points: tuple) -> list[list[float]]:
        out: list[list[float]] = []
        for row in _jsonable(points):
            if not out or row[0] > out[-1][0]:
                out.append(row)
        return out

    return TransferFunction(clean(tf.extinction), clean(tf.albedo))


def _tf_frames(rng: np.random.Generator, tf0: TransferFunction, scenario: str, frames: int,
               edit: str | None) -> tuple[dict, list[TransferFunction]]:
    if scenario != "transfer_function":
        return {"kind": "none"}, [tf0] * frames
    edit = edit or TF_EDITS[int(rng.integers(len(TF_EDITS)))]
    steps = np.arange(frames) / max(frames - 1, 1)
    if edit == "slide":
        end = _r4(rng.uniform(0.1, 0.3) * (1.0 if rng.random() < 0.5 else -1.0))
        return {"kind": "slide", "end_offset": end}, [_rounded(tf0.shifted(_r4(end * s))) for s in steps]
    if edit == "recolour":
        scale = _rgb(rng, 0.3, 1.0)
        target = tf0.recoloured(scale)
        return {"kind": "recolour", "rgb_scale": scale}, [_rounded(tf0.interpolate(target, _r4(s))) for s in steps]
    raise ValueError(f"unknown transfer-function edit {edit!r}; expected one of {TF_EDITS}")


def _orbit(centre: np.ndarray, radius: float, height: float, angle0: float, rate: float, frames: int,
           moving: bool) -> np.ndarray:
    """(frames, 3) points on a horizontal circle around ``centre``; all at angle0 unless ``moving``."""
    angles = angle0 + (rate * np.arange(frames) if moving else np.zeros(frames))
    return np.column_stack([centre[0] + radius * np.cos(angles), np.full(frames, centre[1] + height),
                            centre[2] + radius * np.sin(angles)])


# ---------------------------------------------------------------------------------------------
# Clip
# ---------------------------------------------------------------------------------------------

@dataclass
class VolumeClip:
    """A drawn volumetric clip. ``cameras[t]``: origin, target, up, fov_x_deg, to_world (4x4 list);
    ``lights[t]``: type 'point' (position, intensity) or 'area' (position, target, size, radiance);
    ``transfer_functions[t]``; ``field`` (D, H, W) float32 and its ``field_description`` (manifest entry)."""
    seed: int
    scenario: str
    setting: str
    field: np.ndarray
    field_description: dict
    box_min: list[float]
    box_max: list[float]
    environment: dict
    cameras: list[dict]
    lights: list[dict]
    transfer_functions: list[TransferFunction]
    tf_edit: dict
    max_depth: int = 8

    @property
    def frames(self) -> int:
        return len(self.cameras)

    def manifest(self) -> dict:
        """JSON-ready, complete description (everything but the voxels; see :func:`field_from_manifest`)."""
        return _jsonable({
            "format_version": FORMAT_VERSION, "kind": "volume_clip", "seed": self.seed,
            "scenario": self.scenario, "frames": self.frames, "setting": self.setting,
            "field": self.field_description, "box": {"min": self.box_min, "max": self.box_max},
            "environment": self.environment,
            "integrator": {"type": "mcdn_volpath_features", "max_depth": self.max_depth},
            "transfer_function": {"edit": self.tf_edit, "frames": [tf.to_dict() for tf in self.transfer_functions]},
            "lights": {"frames": self.lights}, "camera": {"frames": self.cameras},
        })

    @classmethod
    def from_manifest(cls, manifest: dict, field: np.ndarray | None = None) -> "VolumeClip":
        """The clip a manifest describes (the field regenerated unless given)."""
        m = copy.deepcopy(manifest)
        return cls(seed=m["seed"], scenario=m["scenario"], setting=m["setting"],
                   field=field_from_manifest(m) if field is None else field, field_description=m["field"],
                   box_min=m["box"]["min"], box_max=m["box"]["max"], environment=m["environment"],
                   cameras=m["camera"]["frames"], lights=m["lights"]["frames"],
                   transfer_functions=[TransferFunction.from_dict(tf) for tf in m["transfer_function"]["frames"]],
                   tf_edit=m["transfer_function"]["edit"], max_depth=m["integrator"]["max_depth"])

    def medium_grids(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(sigma_t (D, H, W), albedo (D, H, W, 3)) of ``frame``'s transfer function applied to the field."""
        return self.transfer_functions[frame].apply(self.field)

    def scene_dict(self, frame: int, *, width: int = 16, height: int = 16, spp: int = 8,
                   medium: bool = True) -> dict:
        """Mitsuba scene dict of ``frame`` (``medium=False`` leaves the volume out, e.g. for comparisons)."""
        import mitsuba as mi

        import scenegen.volumes.integrator  # noqa: F401 -- registers mcdn_volpath_features
        from scenegen.volumes.media import medium_shape

        if not 0 <= frame < self.frames:
            raise IndexError(f"frame {frame} outside clip of {self.frames} frames")
        cam = self.cameras[frame]
        scene: dict[str, Any] = {
            "type": "scene",
            "integrator": {"type": "mcdn_volpath_features", "max_depth": int(self.max_depth)},
            "sensor": {"type": "perspective", "fov": float(cam["fov_x_deg"]), "fov_axis": "x",
                       "to_world": mi.ScalarTransform4f(np.asarray(cam["to_world"], dtype=np.float64)),
                       "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                                "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                       "sampler": {"type": "independent", "sample_count": int(spp)}},
            "light": _light_dict(self.lights[frame], mi),
        }
        grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
        if self.setting == "open":
            scene["environment"] = _environment_dict(self.environment, mi)
            scene["ground"] = {"type": "rectangle", "bsdf": grey,
                               "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale([20, 20, 1])}
        else:
            sx, sy, sz = ROOM_SIZE_M
            room = mi.ScalarTransform4f().translate([0, sy / 2, 0]).scale([sx / 2, sy / 2, sz / 2])
            scene["room"] = {"type": "cube", "flip_normals": True, "bsdf": grey, "to_world": room}
        if medium:
            sigma_t, albedo = self.medium_grids(frame)
            scene[MEDIUM_KEY] = medium_shape(sigma_t, albedo, self.box_min, self.box_max)
        return scene


def _light_dict(light: dict, mi: Any) -> dict:
    if light["type"] == "point":
        return {"type": "point", "position": list(light["position"]),
                "intensity": {"type": "rgb", "value": list(light["intensity"])}}
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f(_area_to_world(light)),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(light["radiance"])}}}


def _area_to_world(light: dict) -> np.ndarray:
    """(4, 4) rectangle to_world: the square [-1, 1]^2 scaled to ``size``, facing ``target`` (+z normal)."""
    half = 0.5 * float(light["size"])
    return look_at_matrix(light["position"], light["target"], UP) @ np.diag([half, half, 1.0, 1.0])


def _environment_dict(env: dict, mi: Any) -> dict:
    if env["kind"] == "constant":
        return {"type": "constant", "radiance": {"type": "rgb", "value": list(env["radiance"])}}
    height, width = env["size"]
    v = (np.arange(height) + 0.5) / height                       # row 0 = zenith (envmap convention, +y up)
    up = np.cos(np.pi * v)[:, None]
    zenith, horizon, ground = (np.asarray(env[k], dtype=np.float64) for k in ("zenith", "horizon", "ground"))
    sky = horizon + np.sqrt(np.clip(up, 0.0, 1.0)) * (zenith - horizon)
    rows = np.where(up >= 0.0, sky, ground)
    image = np.ascontiguousarray(np.broadcast_to(rows[:, None, :], (height, width, 3)), dtype=np.float32)
    return {"type": "envmap", "bitmap": mi.Bitmap(image)}


def generate_volume_clip(seed: int, scenario: str, frames: int, field_kind: str | None = None, *,
                         resolution: int = 24, setting: str | None = None, light_kind: str | None = None,
                         tf_edit: str | None = None, environment: str | None = None, field_npy: str | None = None,
                         transfer_function: dict | None = None, frame_aspect: float = 1.0) -> VolumeClip:
    """Draw a volumetric clip of ``frames`` frames for ``scenario`` (one of SCENARIOS) from ``seed``.

    Bring your own volume: ``field_npy`` names a ``.npy`` scalar field (D, H, W) indexed [z, y, x] that replaces
    the drawn field (see :func:`npy_field_description`; the box takes the array's aspect ratio), and
    ``transfer_function`` ({'extinction': ..., 'albedo': ...}, TransferFunction.from_dict) replaces the drawn
    one (None: drawn as for a cloud). Everything else is drawn from the seed as for a generated clip.

    None for ``field_kind`` / ``setting`` / ``light_kind`` / ``tf_edit`` / ``environment`` draws it from
    the seed (FIELD_KINDS, SETTINGS, LIGHT_KINDS, TF_EDITS -- the latter for 'transfer_function' only --
    and ENVIRONMENTS). ``frame_aspect`` (height / width) lets the camera frame the visible volume. The
    returned clip is rebuilt from its rounded manifest."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; expected one of {SCENARIOS}")
    if int(frames) < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    if not frame_aspect > 0:
        raise ValueError(f"frame_aspect (height / width) must be > 0, got {frame_aspect}")
    frames = int(frames)
    rng_field, rng_tf, rng_place, rng_light, rng_cam, rng_edit = (
        np.random.default_rng(derive_seed(seed, "volume_clip", name))
        for name in ("field", "tf", "placement", "light", "camera", "edit"))

    def pick(value: str | None, options: tuple[str, ...], rng: np.random.Generator, what: str) -> str:
        drawn = options[int(rng.integers(len(options)))]
        if value is not None and value not in options:
            raise ValueError(f"unknown {what} {value!r}; expected one of {options}")
        return value or drawn

    kind = pick(field_kind, FIELD_KINDS, rng_field, "field kind")
    if field_npy is not None:
        field_desc = npy_field_description(field_npy)
        drawn = _draw_transfer_function(rng_tf, {"kind": "noise_cloud"})
        tf0 = _rounded(TransferFunction.from_dict(transfer_function)) if transfer_function is not None else drawn
    else:
        field_desc = _draw_field(rng_field, kind, seed, resolution)
        tf0 = _draw_transfer_function(rng_tf, field_desc)
    edit, tfs = _tf_frames(rng_edit, tf0, scenario, frames, tf_edit)

    setting_ = pick(setting, SETTINGS, rng_place, "setting")
    size = _r4(rng_place.uniform(0.9, 1.5))
    lift = _r4(rng_place.uniform(0.05, 0.4)) if setting_ == "open" else _r4(rng_place.uniform(0.4, 1.0))
    centre = np.array([0.0, lift + size / 2, 0.0])
    # A user's field keeps its aspect ratio: the box's longest side is ``size`` (array axes [z, y, x]).
    aspect = (np.asarray(field_desc["shape"][::-1], dtype=np.float64) / max(field_desc["shape"])
              if field_desc["kind"] == NPY_KIND else np.ones(3))
    box_min, box_max = (centre - size * aspect / 2).tolist(), (centre + size * aspect / 2).tolist()
    env_kind = pick(environment, ENVIRONMENTS, rng_place, "environment")
    if env_kind == "constant":
        env = {"kind": "constant", "radiance": _rgb(rng_place, [0.08, 0.08, 0.1], [0.3, 0.3, 0.4])}
    else:
        env = {"kind": "gradient", "size": list(GRADIENT_MAP_SIZE),
               "zenith": _rgb(rng_place, [0.1, 0.15, 0.3], [0.2, 0.3, 0.6]),
               "horizon": _rgb(rng_place, [0.3, 0.3, 0.3], [0.6, 0.55, 0.5]),
               "ground": _rgb(rng_place, 0.05, 0.15)}

    lkind = pick(light_kind, LIGHT_KINDS, rng_light, "light kind")
    l_radius = _r4(rng_light.uniform(1.4, 2.2))
    l_height = _r4(rng_light.uniform(0.8, 1.6) if setting_ == "open" else rng_light.uniform(0.5, 1.0))
    l_positions = _orbit(centre, l_radius, l_height, rng_light.uniform(0, 2 * np.pi),
                         _r4(rng_light.uniform(0.1, 0.3)) * (1 if rng_light.random() < 0.5 else -1),
                         frames, scenario == "light")
    irradiance = rng_light.uniform(3.0, 8.0)
    colour = rng_light.uniform(0.85, 1.0, 3)
    distance2 = l_radius ** 2 + l_height ** 2
    light_size = _r4(rng_light.uniform(0.2, 0.5))
    lights = []
    for p in l_positions:
        if lkind == "point":
            lights.append({"type": "point", "position": p, "intensity": irradiance * distance2 * colour})
        else:
            lights.append({"type": "area", "position": p, "target": centre, "size": light_size,
                           "radiance": irradiance * distance2 / light_size ** 2 * colour})

    fov = _r4(rng_cam.uniform(35.0, 50.0))
    c_height = _r4(rng_cam.uniform(0.1, 0.6))
    angle0 = rng_cam.uniform(0, 2 * np.pi)
    rate = _r4(rng_cam.uniform(0.05, 0.15)) * (1 if rng_cam.random() < 0.5 else -1)
    field = field_from_description(field_desc)
    lower, upper = occupied_bounds(field, tfs, box_min, box_max)
    target = np.round(0.5 * (lower + upper), FLOAT_DECIMALS)
    # The camera frames what the transfer functions make visible (a small cloud in an empty box would
    # otherwise leave most pixels to the background), from every angle of its orbit.
    angles = angle0 + rate * np.arange(frames) if scenario == "camera" else np.array([angle0])
    c_distance = framing_distance(lower, upper, fov, frame_aspect, c_height, angles)
    if setting_ == "room" and c_distance > ROOM_CAMERA_DISTANCE:
        # The walls hold the camera back: widen the view instead (the spill scales with 1 / tan(fov / 2)).
        c_distance = ROOM_CAMERA_DISTANCE
        spill = framing_spill(lower, upper, fov, frame_aspect, c_height, angles, c_distance)
        fov = _r4(math.degrees(2 * math.atan(math.tan(math.radians(fov) / 2) * spill)) + 1e-3)
    c_radius = orbit_radius(c_distance, c_height)
    origins = _orbit(target, c_radius, c_height, angle0, rate, frames, scenario == "camera")
    cameras = []
    for o in origins:
        o = np.round(o, FLOAT_DECIMALS)
        cameras.append({"origin": o, "target": target, "up": list(UP), "fov_x_deg": fov,
                        "to_world": look_at_matrix(o, target, np.asarray(UP))})

    draft = VolumeClip(seed=int(seed), scenario=scenario, setting=setting_, field=np.zeros((1, 1, 1), np.float32),
                       field_description=field_desc, box_min=box_min, box_max=box_max, environment=env,
                       cameras=cameras, lights=lights, transfer_functions=tfs, tf_edit=edit)
    return VolumeClip.from_manifest(draft.manifest(), field=field)


def frame_updates(scene: Any, clip: VolumeClip, frame: int) -> list[str]:
    """Edit a loaded scene of ``clip`` (``mi.load_dict(clip.scene_dict(s))``) in place so that it renders
    frame ``frame``; returns the edited parameter keys. Only the scenario's element changes: the medium grids
    (``update_medium``) for 'transfer_function', ``sensor.to_world`` for 'camera', ``light.position`` or
    ``light.to_world`` for 'light'. Renders with the same seed are bit-identical to a fresh load of
    ``scene_dict(frame)`` (the test checks this)."""
    import mitsuba as mi

    from scenegen.volumes.media import update_medium

    if not 0 <= frame < clip.frames:
        raise IndexError(f"frame {frame} outside clip of {clip.frames} frames")
    if clip.scenario == "transfer_function":
        sigma_t, albedo = clip.medium_grids(frame)
        prefix = update_medium(scene, sigma_t, albedo, medium=f"{MEDIUM_KEY}.interior_medium")
        return [f"{prefix}.sigma_t.data", f"{prefix}.albedo.data"]
    params = mi.traverse(scene)
    if clip.scenario == "camera":
        key, value = "sensor.to_world", mi.ScalarTransform4f(np.asarray(clip.cameras[frame]["to_world"]))
    elif clip.lights[frame]["type"] == "point":
        key, value = "light.position", mi.Point3f(*clip.lights[frame]["position"])
    else:
        key, value = "light.to_world", mi.ScalarTransform4f(_area_to_world(clip.lights[frame]))
    params[key] = value
    params.update()
    return [key]
