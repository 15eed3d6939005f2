"""Light colours and placements: ceiling area panels, point / spot lights, a constant fill, animated paths.

Intensities are set from a target average floor irradiance (arbitrary linear units, a few units gives
a mean image luminance of order 0.1-1 with the default materials); the generator's luminance check
redraws the scenes that still come out too dark or too bright.
"""
from __future__ import annotations

import functools

import numpy as np

REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
TEMPERATURE_RANGE_K = (2700.0, 7500.0)
FLOOR_IRRADIANCE_RANGE = (3.0, 12.0)
"""Log-uniform range of the target mean floor irradiance shared out among the scene's lights."""


@functools.lru_cache(maxsize=4096)
def _blackbody_rgb_cached(temperature_k: float) -> tuple[float, float, float]:
    import colour  # slow import; only needed when lights are drawn

    xyz = colour.sd_to_XYZ(colour.sd_blackbody(temperature_k))
    rgb = colour.XYZ_to_sRGB(xyz, apply_cctf_encoding=False)
    rgb = np.maximum(rgb, 0.0)
    rgb = rgb / float(rgb @ REC709_LUMINANCE)
    return tuple(float(v) for v in rgb)


def blackbody_rgb(temperature_k: float) -> np.ndarray:
    """Linear sRGB colour (3,) of a black body at `temperature_k` kelvin, normalised to luminance 1."""
    return np.array(_blackbody_rgb_cached(float(temperature_k)))


def draw_temperature(rng: np.random.Generator) -> float:
    """Colour temperature in kelvin, uniform in TEMPERATURE_RANGE_K, rounded to 1 K."""
    return float(np.round(rng.uniform(*TEMPERATURE_RANGE_K)))


def panel_radiance(floor_irradiance: float, floor_area: float, panel_area: float) -> float:
    """Radiance (W sr^-1 m^-2 style units) of a downward Lambertian panel of area `panel_area` m^2 so that,
    assuming half its flux (pi L A) lands on the floor, it adds `floor_irradiance` on average."""
    return 2.0 * floor_irradiance * floor_area / (np.pi * panel_area)


def point_intensity(floor_irradiance: float, floor_area: float) -> float:
    """Radiant intensity (per sr) of an isotropic point light whose flux (4 pi I), ~40 % of it reaching
    the floor, adds `floor_irradiance` on average."""
    return floor_irradiance * floor_area / (0.4 * 4.0 * np.pi)


def spot_intensity(floor_irradiance: float, floor_area: float, cutoff_deg: float) -> float:
    """Intensity of a spot light whose cone flux (2 pi (1 - cos cutoff) I) adds `floor_irradiance` on average."""
    solid_angle = 2.0 * np.pi * (1.0 - np.cos(np.radians(cutoff_deg)))
    return floor_irradiance * floor_area / (0.8 * solid_angle)


def draw_ceiling_panels(rng: np.random.Generator, room_size: np.ndarray, count: int,
                        margin: float = 0.3) -> list[tuple[np.ndarray, np.ndarray]]:
    """Non-overlapping rectangles on the ceiling: list of (centre (x, z), half extents (hx, hz)) in metres."""
    sx, _, sz = room_size
    panels: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(count):
        for _attempt in range(50):
            half = rng.uniform(0.2, 0.75, 2) * np.sqrt(sx * sz / 40.0)
            half = np.minimum(half, [sx / 4, sz / 4])
            lim = np.array([sx / 2, sz / 2]) - half - margin
            centre = rng.uniform(-lim, lim)
            if all(np.any(np.abs(centre - c) > h + half + 0.1) for c, h in panels):
                panels.append((centre, half))
                break
    return panels


def light_box(room_size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners (3,) of the region where point / spot light positions are drawn."""
    sx, sy, sz = room_size
    return (np.array([-sx / 2 + 0.5, 0.5 * sy, -sz / 2 + 0.5]),
            np.array([sx / 2 - 0.5, sy - 0.3, sz / 2 - 0.5]))


def clear_of_spheres(points: np.ndarray, centres: np.ndarray, radii: np.ndarray, margin: float) -> bool:
    """True if none of the (N, 3) points lies within radius + margin of any (M, 3) sphere centre."""
    if len(centres) == 0:
        return True
    dist = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=2)
    return bool(np.all(dist > radii[None, :] + margin))


def draw_light_path(rng: np.random.Generator, start: np.ndarray, n_frames: int, lo: np.ndarray,
                    hi: np.ndarray, vertical: bool = True) -> np.ndarray:
    """(n_frames, 3) positions: a circle (50 %) or a straight back-and-forth line through `start`,
    moving 0.03-0.10 m/frame, clipped to [lo, hi]. `vertical=False` keeps y constant (ceiling panels)."""
    speed = rng.uniform(0.03, 0.10)
    t = np.arange(n_frames, dtype=np.float64)
    if rng.random() < 0.5:
        radius = rng.uniform(0.4, 1.2)
        phase = rng.uniform(0, 2 * np.pi)
        angle = phase + (speed / radius) * t
        offsets = radius * np.column_stack([np.cos(angle) - np.cos(phase), np.zeros(n_frames),
                                            np.sin(angle) - np.sin(phase)])
    else:
        direction = rng.normal(size=3)
        if not vertical:
            direction[1] = 0.0
        direction /= np.linalg.norm(direction)
        amplitude = rng.uniform(0.5, 1.5)
        # Smooth back-and-forth: moves ~speed per frame near the start, never farther than `amplitude`.
        offsets = direction[None, :] * (amplitude * np.sin(speed * t / amplitude))[:, None]
    return np.clip(start[None, :] + offsets, lo, hi)


# ---------------------------------------------------------------------------------------------
# Procedural sky (environment map of open scenes)
# ---------------------------------------------------------------------------------------------

SKY_MAP_SIZE = (128, 256)
"""(height, width) of the latitude-longitude sky image, ~1.4 degrees per pixel."""
SKY_ZENITH_TEMPERATURE_K = (9000.0, 20000.0)
SKY_HORIZON_TEMPERATURE_K = (5500.0, 8000.0)
SUN_TEMPERATURE_K = (4000.0, 6500.0)
SUN_ELEVATION_DEG = (15.0, 65.0)
SUN_WIDTH_DEG = (3.0, 6.0)
"""Standard deviation of the sun's Gaussian lobe: a soft sun, importance-sampled without fireflies."""
SUN_SHARE = (0.3, 0.75)
"""Fraction of the sky's horizontal irradiance that comes from the sun lobe."""
GROUND_REFLECTANCE = 0.25
"""Radiance of the lower hemisphere relative to the horizon (seen only past the ground plane's edge)."""


def latlong_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit world directions (height, width, 3) of the pixel centres of a latitude-longitude map in
    Mitsuba's ``envmap`` convention (u = atan2(x, -z) / 2 pi, v = acos(y) / pi; +y up at the top row),
    and each pixel's solid angle (height, width) in sr."""
    theta = (np.arange(height) + 0.5) * np.pi / height
    phi = (np.arange(width) + 0.5) * 2.0 * np.pi / width
    sin_t = np.sin(theta)[:, None]
    directions = np.stack([sin_t * np.sin(phi)[None, :], np.broadcast_to(np.cos(theta)[:, None], (height, width)),
                           -sin_t * np.cos(phi)[None, :]], axis=-1)
    solid_angle = np.broadcast_to(sin_t * (np.pi / height) * (2.0 * np.pi / width), (height, width))
    return directions, np.ascontiguousarray(solid_angle)


def horizontal_irradiance(image: np.ndarray) -> float:
    """Luminance irradiance on an upward-facing plane from a latitude-longitude radiance map (H, W, 3)."""
    directions, solid_angle = latlong_directions(*image.shape[:2])
    cosine = np.maximum(directions[..., 1], 0.0)
    return float(np.sum((image @ REC709_LUMINANCE) * cosine * solid_angle))


def draw_sky(rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """A clear-sky latitude-longitude radiance map (H, W, 3) float32 with horizontal irradiance 1
    (luminance; scale it by the wanted irradiance), and its parameters for the manifest.

    Upper hemisphere: a blend from a warm, bright horizon to a bluer, darker zenith plus a Gaussian
    sun lobe carrying ``SUN_SHARE`` of the irradiance; lower hemisphere: a dim ground colour."""
    height, width = SKY_MAP_SIZE
    directions, _ = latlong_directions(height, width)
    zenith_k = float(np.round(rng.uniform(*SKY_ZENITH_TEMPERATURE_K)))
    horizon_k = float(np.round(rng.uniform(*SKY_HORIZON_TEMPERATURE_K)))
    sun_k = float(np.round(rng.uniform(*SUN_TEMPERATURE_K)))
    zenith_ratio = float(rng.uniform(0.3, 0.8))
    elevation = np.radians(rng.uniform(*SUN_ELEVATION_DEG))
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    width_rad = np.radians(rng.uniform(*SUN_WIDTH_DEG))
    sun_share = float(rng.uniform(*SUN_SHARE))
    sun_direction = np.array([np.cos(elevation) * np.cos(azimuth), np.sin(elevation),
                              np.cos(elevation) * np.sin(azimuth)])

    up = directions[..., 1:2]
    blend = np.sqrt(np.clip(up, 0.0, 1.0))
    horizon = blackbody_rgb(horizon_k)
    sky = horizon * (1.0 - blend) + zenith_ratio * blackbody_rgb(zenith_k) * blend
    sky = np.where(up >= 0.0, sky, GROUND_REFLECTANCE * horizon)
    angle = np.arccos(np.clip(directions @ sun_direction, -1.0, 1.0))[..., None]
    sun = blackbody_rgb(sun_k) * np.exp(-0.5 * (angle / width_rad) ** 2)
    sky = sky * ((1.0 - sun_share) / horizontal_irradiance(sky))
    sun = sun * (sun_share / horizontal_irradiance(sun))
    image = (sky + sun).astype(np.float32)
    params = {"zenith_temperature_k": zenith_k, "horizon_temperature_k": horizon_k,
              "sun_temperature_k": sun_k, "zenith_ratio": zenith_ratio, "sun_direction": sun_direction,
              "sun_width_deg": float(np.degrees(width_rad)), "sun_share": sun_share}
    return image, params
