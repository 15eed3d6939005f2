"""Training sequences cut from rendered clips: random crops, T-frame sequences, sample layers drawn from the
per-sample stack, and the augmentations of the papers.

One sequence (Chaitanya et al. 2017, §4.3) is made by

1. choosing a clip uniformly and a run of consecutive frames inside one shot (never across a camera
   cut), played forwards or -- with ``backward_prob`` -- backwards;
2. "camera stops": with ``stop_prob`` per frame transition the camera does not advance; the output
   frame repeats the previous source frame (same target, same camera) with fresh noise, i.e. sample
   layers disjoint from the previous frame's whenever the stack has enough layers;
3. ``spp`` of the stored sample layers per output frame (each layer is an independent 1-spp image,
   docs/data-format.md): with ``layers='random'`` (default) drawn without replacement from all stored
   layers and kept in the order drawn, so training sees every stored noise realisation (and a method that
   reads a prefix, NTASD's first k layers per pixel, a random subset even when spp is every stored layer); with ``layers='first'`` always layers
   0..spp-1 (what a renderer producing exactly ``spp`` samples would give), except that a camera stop takes
   the next ``spp`` layers (cyclically) so its noise is fresh whenever the stack has >= 2 spp layers;
4. a square crop, the same for every frame: with ``crops='uniform'`` (default) at a uniform position;
   with ``crops='importance'`` drawn where the noisy input differs most from the reference (Bako et al.
   2017), mixed with uniform by ``importance_floor`` (denoisers/training/crops.py);
5. a random rotation by 0/90/180/270 degrees and (``flip``) a left-right mirror, applied to every
   image buffer; motion vectors and the world-to-view rotation are transformed to match, so
   view-space normals and reprojection stay consistent with the rotated pixel grid;
6. with ``permute_channels`` a random order of the R, G, B channels and with chance ``grayscale_prob`` a
   conversion to CCIR 601 grey (Hasselgren et al. 2020's hue permutation and grayscale augmentation for
   direct prediction), both applied to every colour buffer (radiance-like and albedo) of the input and the
   target alike, so demodulation by the albedo is unchanged; drawn only when switched on, so other configs'
   sequences stay as they were;
7. a per-channel colour modulation drawn from ``color_range`` (paper: [0, 2]) applied to every
   radiance-like buffer of the input and the target (never to albedo, so demodulated colour is
   modulated too).

Validation (:meth:`SequenceConfig.without_augmentation`, :func:`fixed_batches`) always uses random layers
and uniform crops, whatever the training switches say: the validation sequences are a function of the
validation seed only, so every model of a config -- and every arm of a ``layers`` / ``crops`` comparison --
is validated on identical sequences (paired comparisons).

Determinism: batch ``i`` of a dataset is a pure function of (clips, config, seed, i) -- it draws from
its own ``numpy`` generator seeded with (seed, i) -- so a trainer resumes the data stream exactly by
remembering how many batches it used.

Batch layout (torch float32, N sequences of T frames, crop h x w):
``{buffer}`` (N, T, S, C, h, w) per-sample buffers (S = spp); ``reference.{buffer}`` (N, T, C, h, w);
``motion`` (N, T, 2, h, w) pixels, ``valid`` (N, T, 1, h, w) in {0, 1}, ``gbuffer.{key}`` (N, T, C, h, w);
``world_to_view`` (N, T, 3, 3) (view space: x right, y up, z towards the viewer, after augmentation);
``mean.{buffer}`` (N, T, C, h, w) the mean over every stored layer of a per-sample buffer (``mean_buffers``,
e.g. albedo for a method that reads more radiance layers than the other buffers have).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from denoisers.nets.view import MITSUBA_CAMERA_TO_VIEW
from denoisers.training.crops import CROP_MODES, RELATIVE_EPS, ImportanceCrops
from scenegen.dataset import Clip, load_clip

#: Buffers holding radiance: colour modulation scales these (input samples and reference).
RADIANCE_LIKE: frozenset[str] = frozenset({"radiance", "diffuse", "specular", "radiance_half0", "radiance_half1"})
#: Buffers holding colour: hue permutation and grayscale apply to these (radiance-like and albedo).
COLOUR_BUFFERS: frozenset[str] = RADIANCE_LIKE | {"albedo"}
#: CCIR 601 luma weights of the grayscale augmentation (Hasselgren et al. 2020 use them for grey inputs).
GREY_WEIGHTS = np.array([0.2989, 0.587, 0.114], dtype=np.float32)
#: Data switches that are left out of fingerprints and digests while off (added after models were trained).
OPTIONAL_OFF: dict[str, Any] = {"permute_channels": False, "grayscale_prob": 0.0}
#: The augmentations Hasselgren et al. 2020 add for direct prediction only (a variant may differ in these and
#: still count as trained on the same data).
COLOUR_AUGMENTATION_KEYS: tuple[str, ...] = ("permute_channels", "grayscale_prob")
#: Per-pixel buffers a sequence can carry.
PIXEL_KEYS: tuple[str, ...] = ("motion", "valid", "gbuffer.position", "gbuffer.normal", "gbuffer.depth",
                               "gbuffer.object", "gbuffer.albedo", "gbuffer.roughness")
#: One counter-clockwise quarter turn of the image (np.rot90 on (row, column)) in view space (x right, y up).
_QUARTER_TURN_VIEW = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
#: Left-right mirror of the image in view space.
_MIRROR_VIEW = np.diag([-1.0, 1.0, 1.0])
#: How a frame's sample layers are chosen (SequenceConfig.layers).
LAYER_MODES: tuple[str, ...] = ("random", "first")

_CLIP_CACHE: dict[tuple, Clip] = {}


def load_training_clips(render_dirs: Sequence[Path | str], buffers: Sequence[str], *, layers: int | None = None,
                        reference: bool = True) -> list[Clip]:
    """Load clips with :func:`scenegen.dataset.load_clip`, each once per process (cached in memory).

    ``layers`` keeps the first ``layers`` sample layers (None: all stored), which bounds memory.
    """
    clips = []
    for render_dir in render_dirs:
        key = (str(Path(render_dir).resolve()), tuple(buffers), layers, reference)
        if key not in _CLIP_CACHE:
            _CLIP_CACHE[key] = load_clip(Path(render_dir), buffers=list(buffers), spp=layers, reference=reference)
        clips.append(_CLIP_CACHE[key])
    return clips


def clear_clip_cache() -> None:
    """Forget the clips :func:`load_training_clips` cached."""
    _CLIP_CACHE.clear()


@dataclass(frozen=True)
class SequenceConfig:
    """How sequences are cut and augmented (defaults: Chaitanya et al. 2017 §4.3 at 1 spp).

    length: frames per sequence (7); crop: square crop size in pixels, None = whole frames (then no
    rotation of non-square frames); spp: sample layers per frame; rotate / flip: random quarter turns /
    left-right mirror; color_range: per-channel modulation interval or None; backward_prob: chance of
    backward playback; stop_prob: chance per frame transition that the camera stops (the value is ours:
    the paper gives none). sample_buffers / reference_buffers / pixel_buffers: what a batch carries;
    camera: add ``world_to_view`` (needs ``meta[t]['camera']['to_world']``). layers: 'random' (draw from all
    stored layers) or 'first' (layers 0..spp-1; camera stops take the next spp); crops: 'uniform' or
    'importance' (error-weighted, Bako et al. 2017); importance_floor: weight of the uniform distribution
    mixed into importance crops (0..1; > 0 keeps every position reachable; the default 0.2 is ours).
    """

    length: int = 7
    crop: int | None = 128
    spp: int = 1
    rotate: bool = True
    flip: bool = True
    color_range: tuple[float, float] | None = (0.0, 2.0)
    backward_prob: float = 0.5
    stop_prob: float = 0.1
    sample_buffers: tuple[str, ...] = ("radiance", "albedo", "normal", "depth", "roughness")
    reference_buffers: tuple[str, ...] = ("radiance",)
    pixel_buffers: tuple[str, ...] = ()
    mean_buffers: tuple[str, ...] = ()
    camera: bool = True
    layers: str = "random"
    crops: str = "uniform"
    importance_floor: float = 0.2
    permute_channels: bool = False
    grayscale_prob: float = 0.0

    def __post_init__(self) -> None:
        for name in ("sample_buffers", "reference_buffers", "pixel_buffers", "mean_buffers"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if self.color_range is not None:
            object.__setattr__(self, "color_range", tuple(float(c) for c in self.color_range))
            low, high = self.color_range
            if not 0 <= low <= high:
                raise ValueError(f"color_range must be 0 <= low <= high, got {self.color_range}")
        if self.length < 1 or self.spp < 1 or (self.crop is not None and self.crop < 1):
            raise ValueError(f"need length >= 1, spp >= 1, crop >= 1 or None; got {self}")
        if not (0 <= self.backward_prob <= 1 and 0 <= self.stop_prob <= 1):
            raise ValueError(f"backward_prob and stop_prob must lie in [0, 1]; got {self}")
        if self.layers not in LAYER_MODES:
            raise ValueError(f"data key 'layers' = {self.layers!r} is unknown; allowed: {', '.join(LAYER_MODES)}")
        if self.crops not in CROP_MODES:
            raise ValueError(f"data key 'crops' = {self.crops!r} is unknown; allowed: {', '.join(CROP_MODES)}")
        if not 0 <= self.grayscale_prob <= 1:
            raise ValueError(f"data key 'grayscale_prob' = {self.grayscale_prob!r} must lie in [0, 1]")
        if not 0 <= self.importance_floor <= 1:
            raise ValueError(f"data key 'importance_floor' = {self.importance_floor!r} must lie in [0, 1]")
        unknown = [b for b in self.pixel_buffers if b not in PIXEL_KEYS]
        if unknown:
            raise ValueError(f"unknown per-pixel buffers {unknown}; known: {list(PIXEL_KEYS)}")
        # A one-frame sequence played backwards is the same frame: no motion vector links it to another.
        if self.length > 1 and self.backward_prob > 0 and {"motion", "valid"} & set(self.pixel_buffers):
            raise ValueError("backward playback needs forward motion vectors, which are not rendered: "
                             "set backward_prob to 0 when a sequence of more than one frame carries motion/valid")

    def without_augmentation(self) -> "SequenceConfig":
        """The same cut (length, crop, spp, buffers) without any random augmentation, with random layers and
        uniform crops whatever this config's switches (module docstring): for validation."""
        return SequenceConfig(**{**asdict(self), "rotate": False, "flip": False, "color_range": None,
                                 "backward_prob": 0.0, "stop_prob": 0.0, "layers": "random", "crops": "uniform",
                                 "permute_channels": False, "grayscale_prob": 0.0})

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain values; switches added later are left out while off (:data:`OPTIONAL_OFF`), so
        a checkpoint fingerprinted before they existed still resumes."""
        data = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in data.items()
                if not (k in OPTIONAL_OFF and v == OPTIONAL_OFF[k])}


@dataclass(frozen=True)
class SequencePlan:
    """Everything random about one sequence; :meth:`SequenceDataset.sequence` turns it into tensors.

    frames: clip-local frame positions per output frame (equal neighbours = camera stop);
    layers: sample layers per output frame; crop: (row, column) of the crop's top-left corner;
    rotation: counter-clockwise quarter turns; flip: left-right mirror after the rotation;
    color: per-channel factors (1, 1, 1 = none); channels: the source channel of output R, G, B ((0, 1, 2) =
    none); grayscale: colour buffers replaced by their grey.
    """

    clip: int
    scene: str
    frames: tuple[int, ...]
    layers: tuple[tuple[int, ...], ...]
    crop: tuple[int, int]
    rotation: int = 0
    flip: bool = False
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    backward: bool = False
    channels: tuple[int, int, int] = (0, 1, 2)
    grayscale: bool = False

    def describe(self) -> str:
        return (f"{self.scene} frames {list(self.frames)} layers {[list(l) for l in self.layers]} "
                f"crop@{self.crop} rot{90 * self.rotation} flip={self.flip} "
                f"color=({', '.join(f'{c:.3f}' for c in self.color)})"
                + (f" channels={list(self.channels)}" if self.channels != (0, 1, 2) else "")
                + (" grey" if self.grayscale else ""))


@dataclass
class Batch:
    """N sequences: ``tensors`` as in the module docstring, ``plans`` how each was made, ``index`` its number."""

    tensors: dict[str, torch.Tensor]
    plans: list[SequencePlan] = field(default_factory=list)
    index: int = 0

    def __getitem__(self, key: str) -> torch.Tensor:
        return self.tensors[key]

    def __contains__(self, key: str) -> bool:
        return key in self.tensors

    def describe(self) -> str:
        return f"batch {self.index}: " + "; ".join(p.describe() for p in self.plans)


class SequenceDataset:
    """Random training sequences from in-memory clips (see the module docstring)."""

    def __init__(self, clips: Sequence[Clip], config: SequenceConfig | None = None, seed: int = 0) -> None:
        if not clips:
            raise ValueError("a sequence dataset needs at least one clip")
        self.clips = list(clips)
        self.config = config = config or SequenceConfig()
        self.seed = int(seed)
        self._check_clips()
        self._shots = [self._clip_shots(clip) for clip in self.clips]
        longest = max(length for shots in self._shots for _, length in shots)
        if longest < config.length:
            raise ValueError(f"no shot of any clip has {config.length} consecutive frames (longest: {longest}); "
                             f"shorten the sequences or render longer clips")
        # Crop-position distributions of importance crops: computed once per clip.
        self._importance = ([ImportanceCrops(clip, config.crop) for clip in self.clips]
                            if config.crops == "importance" and config.crop is not None else None)

    # ----------------------------------------------------------------------------------- checks
    def _check_clips(self) -> None:
        config = self.config
        for clip in self.clips:
            for buffer in (*config.sample_buffers, *config.mean_buffers):
                if buffer not in clip.samples:
                    raise KeyError(f"clip {clip.scene!r} has no per-sample buffer {buffer!r} "
                                   f"(loaded: {', '.join(clip.samples)})")
            if config.reference_buffers and (clip.reference is None or
                                             any(b not in clip.reference for b in config.reference_buffers)):
                loaded = list(clip.reference or {})
                raise KeyError(f"clip {clip.scene!r} lacks reference buffers {list(config.reference_buffers)} "
                               f"(loaded: {loaded}; feature means need render.reference_integrator: features)")
            for key in config.pixel_buffers:
                if key.startswith("gbuffer.") and key.split(".", 1)[1] not in clip.gbuffer:
                    raise KeyError(f"clip {clip.scene!r} has no G-buffer {key!r}")
            if self._layers(clip) < config.spp:
                raise ValueError(f"clip {clip.scene!r} has {self._layers(clip)} sample layers, "
                                 f"fewer than spp={config.spp}")
            height, width = clip.motion.shape[-2:]
            if config.crop is not None and (height < config.crop or width < config.crop):
                raise ValueError(f"clip {clip.scene!r} is {height}x{width} pixels, smaller than the crop {config.crop}")
            if config.camera:
                for t, meta in enumerate(clip.meta):
                    if "to_world" not in (meta.get("camera") or {}):
                        raise KeyError(f"clip {clip.scene!r} frame {clip.frames[t]} has no camera "
                                       f"(meta['camera']['to_world']), needed for view-space normals")

    def _layers(self, clip: Clip) -> int:
        """Sample layers usable for every requested buffer (radiance may have extra layers)."""
        return min(clip.samples[b].shape[1] for b in self.config.sample_buffers) if self.config.sample_buffers \
            else 1

    @staticmethod
    def _clip_shots(clip: Clip) -> list[tuple[int, int]]:
        """(first position, length) of each shot: runs of frames without a camera cut inside."""
        n = len(clip.frames)
        starts = [0] + [t for t in range(1, n) if t < len(clip.meta) and clip.meta[t].get("camera_cut", False)]
        return [(start, end - start) for start, end in zip(starts, starts[1:] + [n])]

    # ---------------------------------------------------------------------------------- planning
    def generator(self, index: int, stream: int = 0) -> np.random.Generator:
        """The generator of batch ``index`` (``stream`` separates independent uses of the same seed)."""
        return np.random.default_rng(np.random.SeedSequence([self.seed, stream, int(index)]))

    def plan(self, rng: np.random.Generator) -> SequencePlan:
        """Draw one sequence's clip, frames, layers, crop and augmentation."""
        config = self.config
        stops = rng.random(config.length - 1) < config.stop_prob if config.length > 1 else np.zeros(0, bool)
        n_source = config.length - int(stops.sum())
        candidates = [i for i, shots in enumerate(self._shots) if any(length >= n_source for _, length in shots)]
        clip_index = candidates[int(rng.integers(len(candidates)))]
        clip = self.clips[clip_index]
        starts = [start + offset for start, length in self._shots[clip_index]
                  for offset in range(length - n_source + 1)]
        first = starts[int(rng.integers(len(starts)))]
        source = list(range(first, first + n_source))
        backward = bool(rng.random() < config.backward_prob)
        if backward:
            source.reverse()
        frames = [source[0]]
        cursor = 0
        for stopped in stops:
            cursor += 0 if stopped else 1
            frames.append(source[cursor])

        layers = self._plan_layers(rng, frames, self._layers(clip))

        height, width = clip.motion.shape[-2:]
        crop = config.crop
        if self._importance is not None:
            row, column = self._importance[clip_index].draw(rng, frames, config.importance_floor)
        else:
            row = int(rng.integers(height - crop + 1)) if crop is not None else 0
            column = int(rng.integers(width - crop + 1)) if crop is not None else 0
        square = crop is not None or height == width
        rotation = int(rng.integers(4)) if config.rotate and square else 0
        flip = bool(rng.random() < 0.5) if config.flip else False
        if config.color_range is not None:
            color = tuple(float(c) for c in rng.uniform(*config.color_range, size=3))
        else:
            color = (1.0, 1.0, 1.0)
        # Drawn only when switched on: configs without them keep their random streams (and sequences).
        channels = tuple(int(c) for c in rng.permutation(3)) if config.permute_channels else (0, 1, 2)
        grayscale = bool(rng.random() < config.grayscale_prob) if config.grayscale_prob > 0 else False
        return SequencePlan(clip=clip_index, scene=clip.scene, frames=tuple(frames), layers=tuple(layers),
                            crop=(row, column), rotation=rotation, flip=flip, color=color, backward=backward,
                            channels=channels, grayscale=grayscale)

    def _plan_layers(self, rng: np.random.Generator, frames: Sequence[int], n_layers: int) -> list[tuple[int, ...]]:
        """Sample layers per output frame (``config.layers``); a camera stop gets layers disjoint from the
        previous frame's whenever ``n_layers`` allows it. 'first' draws nothing from ``rng``."""
        spp = self.config.spp
        layers: list[tuple[int, ...]] = []
        start = 0
        for i, t in enumerate(frames):
            stop = i > 0 and frames[i - 1] == t
            if self.config.layers == "first":
                # The next spp layers after the previous frame's block (cyclically) at a stop, else 0..spp-1.
                start = (start + spp) % n_layers if stop and n_layers >= 2 * spp else 0
                block = np.sort((start + np.arange(spp)) % n_layers)
                layers.append(tuple(int(s) for s in block))
                continue
            pool = np.arange(n_layers)
            if stop:
                fresh = np.setdiff1d(pool, layers[-1])
                if fresh.size >= spp:
                    pool = fresh
            # In the order drawn: a method that reads a prefix of the layers (NTASD's first k per pixel) then
            # sees a random subset of the stored layers, not always layers 0..k-1.
            layers.append(tuple(int(s) for s in rng.choice(pool, spp, replace=False)))
        return layers

    # ----------------------------------------------------------------------------- materialising
    def sequence(self, plan: SequencePlan) -> dict[str, torch.Tensor]:
        """Tensors of one planned sequence, shapes as in the module docstring without the N axis."""
        config = self.config
        clip = self.clips[plan.clip]
        height, width = clip.motion.shape[-2:]
        crop_h = config.crop if config.crop is not None else height
        crop_w = config.crop if config.crop is not None else width
        rows = slice(plan.crop[0], plan.crop[0] + crop_h)
        columns = slice(plan.crop[1], plan.crop[1] + crop_w)
        frames = np.asarray(plan.frames)
        layers = np.asarray(plan.layers)
        color = np.asarray(plan.color, dtype=np.float32).reshape(3, 1, 1)
        out: dict[str, np.ndarray] = {}

        def recolour(buffer: str, data: np.ndarray) -> np.ndarray:
            """Hue permutation, grayscale, then the colour modulation of one buffer (channels on axis -3)."""
            if buffer in COLOUR_BUFFERS:
                if plan.channels != (0, 1, 2):
                    data = data[..., list(plan.channels), :, :]
                if plan.grayscale:
                    grey = np.tensordot(data, GREY_WEIGHTS, axes=([-3], [0]))[..., None, :, :]
                    data = np.repeat(grey, 3, axis=-3)
            return data * color if buffer in RADIANCE_LIKE else data

        for buffer in config.sample_buffers:
            data = clip.samples[buffer][:, :, :, rows, columns][frames[:, None], layers]   # (T, S, C, h, w)
            out[buffer] = recolour(buffer, data)
        for buffer in config.mean_buffers:
            data = clip.samples[buffer][:, :, :, rows, columns][frames].mean(axis=1)           # (T, C, h, w)
            out[f"mean.{buffer}"] = recolour(buffer, data)
        for buffer in config.reference_buffers:
            data = clip.reference[buffer][:, :, rows, columns][frames]
            out[f"reference.{buffer}"] = recolour(buffer, data)
        stopped = np.concatenate([[False], frames[1:] == frames[:-1]])
        for key in config.pixel_buffers:
            if key == "motion":
                data = np.where(stopped[:, None, None, None], 0.0, clip.motion[:, :, rows, columns][frames])
            elif key == "valid":
                data = np.where(stopped[:, None, None, None], True, clip.valid[:, :, rows, columns][frames])
            else:
                data = clip.gbuffer[key.split(".", 1)[1]][:, :, rows, columns][frames]
                if key == "gbuffer.albedo":           # permuted and greyed like the per-sample albedo
                    data = recolour("albedo", data)
            out[key] = data.astype(np.float32)
        out = {key: _orient(value, plan.rotation, plan.flip) for key, value in out.items()}
        if "motion" in out:
            out["motion"] = _orient_motion(out["motion"], plan.rotation, plan.flip)
        tensors = {key: torch.from_numpy(np.ascontiguousarray(value, dtype=np.float32)) for key, value in out.items()}
        if config.camera:
            transform = image_transform_view(plan.rotation, plan.flip)
            rotations = [transform @ MITSUBA_CAMERA_TO_VIEW @ np.asarray(clip.meta[t]["camera"]["to_world"],
                                                                  dtype=np.float64)[:3, :3].T for t in plan.frames]
            tensors["world_to_view"] = torch.from_numpy(np.stack(rotations)).float()
        return tensors

    def batch(self, index: int, batch_size: int, stream: int = 0) -> Batch:
        """Batch number ``index`` of ``batch_size`` sequences; the same arguments always give the same batch."""
        rng = self.generator(index, stream)
        plans = [self.plan(rng) for _ in range(batch_size)]
        sequences = [self.sequence(plan) for plan in plans]
        shapes = {tuple(s["radiance" if "radiance" in s else next(iter(s))].shape) for s in sequences}
        if len(shapes) > 1:
            raise ValueError(f"sequences of one batch differ in size {sorted(shapes)}: use a crop or batch size 1")
        tensors = {key: torch.stack([s[key] for s in sequences]) for key in sequences[0]}
        return Batch(tensors=tensors, plans=plans, index=int(index))

    def describe(self) -> dict[str, Any]:
        """What determines the data stream (for a checkpoint's fingerprint)."""
        crops = {"crop_error": {"eps": RELATIVE_EPS, "frames": "mean"}} if self.config.crops == "importance" else {}
        return {"config": self.config.to_dict(), "seed": self.seed, **crops,
                "clips": [{"scene": c.scene, "frames": [int(f) for f in c.frames],
                           "layers": self._layers(c), "size": list(c.motion.shape[-2:])} for c in self.clips]}


def fixed_batches(clips: Sequence[Clip], config: SequenceConfig, count: int, batch_size: int = 1,
                  seed: int = 0) -> list[Batch]:
    """``count`` deterministic batches without augmentation (validation): same clips, crops and layers every time."""
    dataset = SequenceDataset(clips, config.without_augmentation(), seed=seed)
    return [dataset.batch(i, batch_size, stream=1) for i in range(count)]


# ----------------------------------------------------------------------------------- orientation
def image_transform_view(rotation: int, flip: bool) -> np.ndarray:
    """(3, 3) view-space map of ``rotation`` counter-clockwise quarter turns followed by an optional
    left-right mirror of the image: what happens to a view-space vector when the image is re-oriented."""
    matrix = np.linalg.matrix_power(_QUARTER_TURN_VIEW, rotation % 4)
    return _MIRROR_VIEW @ matrix if flip else matrix


def _orient(image: np.ndarray, rotation: int, flip: bool) -> np.ndarray:
    """Rotate (counter-clockwise quarter turns) then mirror left-right the last two axes of (..., H, W)."""
    if rotation % 4:
        image = np.rot90(image, rotation % 4, axes=(-2, -1))
    return image[..., ::-1] if flip else image


def _orient_motion(motion: np.ndarray, rotation: int, flip: bool) -> np.ndarray:
    """Re-express (..., 2, H, W) pixel motion (x right, y down) after :func:`_orient` of its pixel grid."""
    mx, my = motion[..., 0, :, :], motion[..., 1, :, :]
    for _ in range(rotation % 4):
        # A counter-clockwise quarter turn maps image-right to image-up (-y) and image-down to image-right.
        mx, my = my, -mx
    if flip:
        mx = -mx
    return np.stack([mx, my], axis=-3)

