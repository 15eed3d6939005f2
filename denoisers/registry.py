"""One interface for every denoising method, and the registry that names them.

A method is one module with one ``@register(...)`` decorated class. The decorator declares what the
method reads (per-sample buffers, per-pixel buffers), whether it trains and whether it is temporal.
Every method is run the same way: ``reset()`` at the start of a clip, then ``denoise(frame)`` once
per frame in order. A temporal method keeps its own history between calls (so it can run on a
stream); a single-frame method ignores it.

Adding a method = one module under ``denoisers/methods/`` plus one entry in the config's
``evaluation.methods``; ``denoisers.methods`` imports every module so the registry is complete.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Iterator, Sequence

import numpy as np
import torch

from denoisers.errors import MissingInputError  # noqa: F401 (raised by methods, imported from here)
from scenegen.channels import PIXEL_BUFFERS, SAMPLE_BUFFERS

# Per-pixel inputs a method may declare, besides the PIXEL_BUFFERS of the data format.
PIXEL_INPUTS: frozenset[str] = frozenset(PIXEL_BUFFERS)


@dataclass(frozen=True)
class MethodInfo:
    """What a registered method declares about itself."""

    name: str
    inputs: tuple[str, ...]               # per-sample buffers, names of scenegen.channels.SAMPLE_BUFFERS
    pixel_inputs: tuple[str, ...] = ()    # per-pixel buffers, names of scenegen.channels.PIXEL_BUFFERS
    trainable: bool = False
    temporal: bool = False
    description: str = ""
    # Adaptive sampling (denoisers.adaptive): the method receives every stored layer and an average
    # budget (Frame.budget) and returns an AdaptiveOutput with its per-pixel sample map.
    adaptive: bool = False


@dataclass
class Frame:
    """One frame as a method sees it. Tensors are float32 on the CPU.

    samples: buffer -> (S, C, H, W) per-sample values (S = the spp being evaluated);
    pixel: buffer -> (C, H, W) per-pixel values ("motion" in pixels with prev = centre + motion,
    "valid" in {0, 1}); index: frame index in the clip; camera_cut: no usable history.

    Adaptive methods (MethodInfo.adaptive): ``samples`` holds every stored layer, so "radiance" has
    render.spp + render.extra_radiance_spp layers and every other buffer only the first render.spp
    (the radiance-only extra layers have no auxiliary buffers; ``spp`` is then the first buffer's
    layer count); ``budget`` is the average spp the method may spend (the evaluated spp), None otherwise.
    """

    samples: dict[str, torch.Tensor]
    pixel: dict[str, torch.Tensor] = field(default_factory=dict)
    index: int = 0
    camera_cut: bool = False
    meta: dict = field(default_factory=dict)
    budget: float | None = None

    @property
    def spp(self) -> int:
        return next(iter(self.samples.values())).shape[0]

    @property
    def height(self) -> int:
        return next(iter(self.samples.values())).shape[-2]

    @property
    def width(self) -> int:
        return next(iter(self.samples.values())).shape[-1]

    def mean(self, buffer: str) -> torch.Tensor:
        """(C, H, W) box-filtered mean of a per-sample buffer over the frame's samples."""
        return self.samples[buffer].mean(dim=0)

    def to(self, device: torch.device | str) -> "Frame":
        """This frame with its sample and pixel tensors on ``device`` (the same frame on its own device)."""
        device = torch.device(device)
        if all(t.device == device for t in (*self.samples.values(), *self.pixel.values())):
            return self
        return Frame({k: v.to(device) for k, v in self.samples.items()},
                     {k: v.to(device) for k, v in self.pixel.items()},
                     self.index, self.camera_cut, self.meta, self.budget)


@dataclass
class AdaptiveOutput:
    """What an adaptive method's ``denoise`` returns: radiance (3, H, W) linear HDR and the integer
    (H, W) sample map it used (pixel p read the first sample_map[p] radiance layers; its mean must not
    exceed Frame.budget, see denoisers.adaptive.budget_total)."""

    radiance: torch.Tensor
    sample_map: torch.Tensor


class Denoiser:
    """Base class of every method. Subclasses set nothing by hand: ``@register`` sets ``info``.

    ``samples_factor``: the method receives this many times the evaluated spp (1 for denoisers;
    the path-tracing reference row uses it for its equal-time comparison).
    """

    info: ClassVar[MethodInfo]
    samples_factor: int = 1
    #: Where denoise() computes (:meth:`to`); frames arrive there (denoisers.jobs.denoise.run_method).
    device: torch.device = torch.device("cpu")

    def __init__(self, **params: Any) -> None:
        if params:
            raise TypeError(f"method {self.info.name!r} takes no parameters {sorted(params)}")

    def to(self, device: torch.device | str) -> "Denoiser":
        """Compute on ``device`` from now on (config ``compute.device``; a loaded network moves with it).
        Returns ``self``. Subclasses holding tensors or a network override :meth:`_moved`."""
        self.device = torch.device(device)
        self._moved()
        return self

    def _moved(self) -> None:
        """Called by :meth:`to` after ``self.device`` changed: move what the method holds."""

    def reset(self) -> None:
        """Forget all temporal state (start of a clip). Single-frame methods need not override."""

    def denoise(self, frame: Frame) -> torch.Tensor:
        """Return the denoised linear HDR radiance (3, H, W) of ``frame``."""
        raise NotImplementedError

    def diagnostics(self) -> dict[str, torch.Tensor]:
        """Per-pixel maps (H, W) the last denoise() computed that a report may show (e.g. AFN's temporal
        weight lambda); the evaluation stores them per frame in ``maps.npz``. None by default."""
        return {}


_REGISTRY: dict[str, type[Denoiser]] = {}


def register(name: str, *, inputs: Sequence[str], pixel_inputs: Sequence[str] = (), trainable: bool = False,
             temporal: bool = False, description: str = "", adaptive: bool = False
             ) -> Callable[[type[Denoiser]], type[Denoiser]]:
    """Class decorator adding a method to the registry under ``name``."""
    unknown = [b for b in inputs if b not in SAMPLE_BUFFERS] + [b for b in pixel_inputs if b not in PIXEL_INPUTS]
    if unknown:
        raise ValueError(f"method {name!r} declares unknown buffers {unknown}; per-sample buffers are "
                         f"{sorted(SAMPLE_BUFFERS)}, per-pixel buffers {sorted(PIXEL_INPUTS)}")

    def decorate(cls: type[Denoiser]) -> type[Denoiser]:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ValueError(f"method name {name!r} is registered twice")
        cls.info = MethodInfo(name=name, inputs=tuple(inputs), pixel_inputs=tuple(pixel_inputs),
                              trainable=trainable, temporal=temporal,
                              description=description or (cls.__doc__ or "").strip().split("\n")[0],
                              adaptive=adaptive)
        _REGISTRY[name] = cls
        return cls

    return decorate


def available() -> list[str]:
    """Names of all registered methods."""
    import denoisers.methods  # noqa: F401 -- imports every method module

    return sorted(_REGISTRY)


def get(name: str) -> type[Denoiser]:
    """The class registered as ``name``; KeyError listing the known names otherwise."""
    names = available()
    if name not in _REGISTRY:
        raise KeyError(f"unknown denoising method {name!r}; registered methods: {', '.join(names)}")
    return _REGISTRY[name]


def parameters(name: str) -> dict[str, Any]:
    """Constructor parameters of method ``name`` and their defaults (``inspect.Parameter.empty`` if required)."""
    import inspect

    signature = inspect.signature(get(name).__init__)
    return {p.name: p.default for p in list(signature.parameters.values())[1:]
            if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def build(name: str, params: dict[str, Any] | None = None, row: str | None = None) -> Denoiser:
    """Instantiate method ``name`` with its parameters from the config; an unknown parameter is a
    ValueError naming the row, the method, the allowed parameters and the closest one."""
    import difflib

    import inspect

    params = dict(params or {})
    allowed = parameters(name)
    open_ended = any(p.kind == p.VAR_KEYWORD for p in inspect.signature(get(name).__init__).parameters.values())
    unknown = [] if open_ended else [key for key in params if key not in allowed]
    if unknown:
        where = f"evaluation row {row!r} (method {name!r})" if row else f"method {name!r}"
        hints = [f"{key!r}" + (f" (did you mean {close[0]!r}?)" if (close := difflib.get_close_matches(
            key, list(allowed), n=1)) else "") for key in unknown]
        raise ValueError(f"{where}: unknown parameter(s) {', '.join(hints)}; allowed: "
                         f"{', '.join(allowed) or 'none'}")
    return get(name)(**params)


def check_inputs(info: MethodInfo, sample_buffers: Sequence[str], pixel_buffers: Sequence[str],
                 where: str = "") -> None:
    """Raise MissingInputError if any declared input is not among the available buffers."""
    for buffer in info.inputs:
        if buffer not in sample_buffers:
            raise MissingInputError(info.name, buffer, where)
    for buffer in info.pixel_inputs:
        if buffer not in pixel_buffers:
            raise MissingInputError(info.name, buffer, where)


def clip_frames(clip, info: MethodInfo, spp: int, budget: float | None = None) -> Iterator[Frame]:
    """Frames of a loaded ``scenegen.dataset.Clip`` with exactly the buffers ``info`` declares.

    ``spp`` takes the first ``spp`` sample layers. Raises MissingInputError naming the buffer and
    the method when the clip lacks a declared input. For an adaptive method (``info.adaptive``) every
    loaded layer is kept (``spp`` is the least radiance layers needed) and ``budget`` (default ``spp``)
    becomes Frame.budget.
    """
    if info.adaptive and budget is None:
        budget = float(spp)
    check_inputs(info, list(clip.samples), ["motion", "valid", *(f"gbuffer.{k}" for k in clip.gbuffer)],
                 where=f"scene {clip.scene}")
    for t, frame_index in enumerate(clip.frames):
        samples = {}
        for buffer in info.inputs:
            stack = clip.samples[buffer]
            needed = (spp if buffer == "radiance" else 1) if info.adaptive else spp
            if stack.shape[1] < needed:
                raise MissingInputError(info.name, buffer, f"{needed} spp asked, {stack.shape[1]} layers rendered")
            samples[buffer] = torch.from_numpy(np.ascontiguousarray(stack[t] if info.adaptive else stack[t, :spp]))
        pixel = {}
        for buffer in info.pixel_inputs:
            if buffer == "motion":
                pixel[buffer] = torch.from_numpy(np.ascontiguousarray(clip.motion[t]))
            elif buffer == "valid":
                pixel[buffer] = torch.from_numpy(clip.valid[t].astype(np.float32))
            else:
                pixel[buffer] = torch.from_numpy(np.ascontiguousarray(clip.gbuffer[buffer.split(".", 1)[1]][t]))
        meta = clip.meta[t] if t < len(clip.meta) else {}
        yield Frame(samples=samples, pixel=pixel, index=frame_index,
                    camera_cut=bool(meta.get("camera_cut", False)), meta=meta,
                    budget=budget if info.adaptive else None)
