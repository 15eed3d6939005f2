"""Hasselgren et al. 2020 (NTASD) and its variants as evaluation methods: trained networks
(denoisers.nets.ntasd) streamed frame by frame, the warped previous output carried between frames.

Every variant is an adaptive method (registry ``adaptive=True``): it receives every stored radiance layer
and the row's average budget and returns its sample map, so the evaluation checks the budget of all of
them alike. The uniform variants spend exactly the budget in every pixel (the first n layers: the same
input as the ``noisy`` row at n spp); ``budget_factor`` k makes a row spend k times the evaluated spp (the
"uniform 8 spp" curve of Fig. 7 is ``ntasd_uniform`` with k = 2 at 4 spp).

Registry names (training task and row need the same name): ``ntasd`` temporal adaptive, ``ntasd_uniform``
temporal uniform, ``ntasd_kpn`` per-frame kernel prediction, ``ntasd_direct`` per-frame direct prediction,
``dasr`` per-frame adaptive sampling from a 1-spp initial pass (Kuznetsov et al. 2018, with the same
U-Net and kernel-predicting denoiser, as Hasselgren et al. altered it).
"""
from __future__ import annotations

from pathlib import Path

import torch

from denoisers.filters import check_sizes
from denoisers.nets import for_inference
from denoisers.nets.ntasd import NTASDNet, decode
from denoisers.nets.ntasd_task import FrameInputs, frame_step
from denoisers.nets.view import world_to_view
from denoisers.registry import AdaptiveOutput, Denoiser, Frame, register
from denoisers.training.tasks import NTASD_VARIANTS

INPUTS = ("radiance", "albedo")

PIXEL_INPUTS = ("motion", "valid", "gbuffer.normal", "gbuffer.depth")


class NTASDDenoiser(Denoiser):
    """A trained NTASD variant. Parameters: ``checkpoint`` (required; a model or training checkpoint of this
    variant, best.pt); ``budget_factor`` (1): the row spends budget_factor x the evaluated spp.

    Per frame: radiance layers (all stored), mean albedo over its stored layers, the G-buffer normal (rotated
    to view space with the frame's camera) and depth, motion and validity; the history (the previous
    encoded output) is dropped at a camera cut. Output: the decoded network output, and the sample map.
    """

    def __init__(self, checkpoint: str | None = None, budget_factor: int = 1) -> None:
        super().__init__()
        if not checkpoint:
            raise ValueError(f"method {self.info.name!r} needs params.checkpoint: the path of a trained model "
                             "(best.pt); in a config, name a trained model instead with params {model: <id>}")
        if int(budget_factor) < 1:
            raise ValueError(f"method {self.info.name!r}: budget_factor must be >= 1, got {budget_factor}")
        self.checkpoint = Path(checkpoint)
        self.samples_factor = int(budget_factor)
        self._model: NTASDNet | None = None
        self._history: torch.Tensor | None = None

    @classmethod
    def from_model(cls, model: NTASDNet, budget_factor: int = 1) -> "NTASDDenoiser":
        """The method around an in-memory network (tests, benchmarks)."""
        method = cls.__new__(cls)
        Denoiser.__init__(method)
        method.checkpoint, method.samples_factor = None, int(budget_factor)
        method._model, method._history = for_inference(model), None
        method._check_variant(model)
        return method

    def _check_variant(self, model: torch.nn.Module) -> None:
        expected = NTASD_VARIANTS[self.info.name]
        found = (getattr(model.config, "variant", None), getattr(model.config, "sampling", None))
        if not isinstance(model, NTASDNet) or found != expected:
            raise TypeError(f"{self.checkpoint}: holds {type(model).__name__} {found}, not the {self.info.name!r} "
                            f"variant {expected} (variant, sampling)")

    @property
    def model(self) -> NTASDNet:
        if self._model is None:
            from denoisers.training.checkpoints import load_model

            model = load_model(self.checkpoint)
            self._check_variant(model)
            self._model = for_inference(model).to(self.device)
        return self._model

    def _moved(self) -> None:
        if self._model is not None:
            self._model = self._model.to(self.device)
        self.reset()

    def reset(self) -> None:
        self._history = None

    def denoise(self, frame: Frame) -> AdaptiveOutput:
        check_sizes(self.info.name, {"albedo": frame.samples["albedo"]})
        camera = frame.meta.get("camera") or {}
        if "to_world" not in camera:
            raise ValueError(f"method {self.info.name!r} needs the camera (frame.meta['camera']['to_world']) to "
                             f"express normals in view space; frame {frame.index} has none")
        if frame.budget is None:
            raise ValueError(f"method {self.info.name!r}, frame {frame.index}: the frame carries no budget")
        if frame.camera_cut:
            self._history = None
        inputs = FrameInputs(layers=frame.samples["radiance"][None], albedo=frame.mean("albedo")[None],
                             normal=frame.pixel["gbuffer.normal"][None], depth=frame.pixel["gbuffer.depth"][None],
                             motion=frame.pixel["motion"][None], valid=frame.pixel["valid"][None],
                             world_to_view=world_to_view(camera["to_world"]).to(self.device)[None])
        step = frame_step(self.model, inputs, self._history, float(frame.budget))
        self._history = step.output if self.model.config.temporal else None
        radiance = torch.nan_to_num(decode(step.output[0]), nan=0.0, posinf=0.0, neginf=0.0)
        return AdaptiveOutput(radiance, step.counts[0])


_DESCRIPTIONS = {
    "ntasd": "NTASD temporal adaptive (Hasselgren et al. 2020): sample-map network + recurrent multi-scale KPN, trained",
    "ntasd_uniform": "NTASD temporal, uniform sampling (Hasselgren et al. 2020 'Our uniform'), trained",
    "ntasd_kpn": "per-frame three-level kernel-predicting U-Net (Hasselgren et al. 2020 'KPN'), trained",
    "ntasd_direct": "per-frame U-Net predicting colour directly (Hasselgren et al. 2020 'Direct prediction'), trained",
    "dasr": "deep adaptive sampling and reconstruction (Kuznetsov et al. 2018) with NTASD's U-Nets, per frame, trained",
}

for _name, (_variant, _sampling) in NTASD_VARIANTS.items():
    register(_name, inputs=INPUTS, pixel_inputs=PIXEL_INPUTS, trainable=True, temporal=_variant == "temporal",
             adaptive=True, description=_DESCRIPTIONS[_name])(type(f"NTASD_{_name}", (NTASDDenoiser,), {}))
