"""KPCN (Bako et al. 2017) as an evaluation method: a trained pair of kernel-predicting networks
(denoisers.nets.kpcn) applied to every frame on its own (denoisers.nets.kpcn_task.frame_step)."""
from __future__ import annotations

from pathlib import Path

import torch

from denoisers.filters import check_sizes
from denoisers.nets import for_inference
from denoisers.nets.kpcn import KPCNNet
from denoisers.nets.kpcn_task import SAMPLE_BUFFERS, frame_step
from denoisers.nets.view import world_to_view
from denoisers.registry import Denoiser, Frame, register


@register("kpcn", inputs=SAMPLE_BUFFERS, trainable=True, temporal=False,
          description="kernel-predicting convolutional networks (Bako et al. 2017): diffuse (demodulated) and "
                      "specular (log) networks predicting 17 x 17 softmax kernels per pixel; trained")
class KPCNDenoiser(Denoiser):
    """A trained KPCN. Parameters: ``checkpoint`` (required; best.pt of a ``kpcn`` model).

    Per frame: the per-sample diffuse, specular, albedo, normal (rotated to view space with the frame's camera)
    and depth; the output is diffuse' x (albedo + 0.00316) + exp(specular') - 1. No state between frames.
    """

    def __init__(self, checkpoint: str | None = None) -> None:
        super().__init__()
        if not checkpoint:
            raise ValueError("method 'kpcn' needs params.checkpoint: the path of a trained model (best.pt); in a "
                             "config, name a trained model instead with params {model: <id>}")
        self.checkpoint = Path(checkpoint)
        self._model: KPCNNet | None = None

    @classmethod
    def from_model(cls, model: KPCNNet) -> "KPCNDenoiser":
        """The method around an in-memory network (tests, benchmarks)."""
        method = cls.__new__(cls)
        Denoiser.__init__(method)
        method.checkpoint, method._model = None, for_inference(model)
        return method

    @property
    def model(self) -> KPCNNet:
        if self._model is None:
            from denoisers.training.checkpoints import load_model

            model = load_model(self.checkpoint)
            if not isinstance(model, KPCNNet):
                raise TypeError(f"{self.checkpoint}: holds a {type(model).__name__}, not a KPCN")
            self._model = for_inference(model).to(self.device)
        return self._model

    def _moved(self) -> None:
        if self._model is not None:
            self._model = self._model.to(self.device)
        self.reset()

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        camera = frame.meta.get("camera") or {}
        if "to_world" not in camera:
            raise ValueError(f"method 'kpcn' needs the camera (frame.meta['camera']['to_world']) to express normals "
                             f"in view space; frame {frame.index} has none")
        samples = {b: frame.samples[b][None] for b in SAMPLE_BUFFERS}
        with torch.no_grad():
            step = frame_step(self.model, samples, world_to_view(camera["to_world"]).to(self.device)[None])
        return torch.nan_to_num(step.output[0], nan=0.0, posinf=0.0, neginf=0.0)
