"""Isik et al. 2021 (affinity of neural features) as an evaluation method: a trained network
(denoisers.nets.afn) streamed frame by frame, its history (accumulated embedding and radiance, last-kernel
features, output) carried between frames and dropped at a camera cut."""
from __future__ import annotations

from pathlib import Path

import torch

from denoisers.filters import check_sizes
from denoisers.nets import for_inference
from denoisers.nets.afn import AFNNet
from denoisers.nets.afn_task import SAMPLE_BUFFERS, History, frame_step, sample_features
from denoisers.nets.view import world_to_view
from denoisers.registry import Denoiser, Frame, register


@register("afn", inputs=SAMPLE_BUFFERS, pixel_inputs=("motion", "valid"), trainable=True, temporal=True,
          description="affinity of neural features (Isik et al. 2021): per-sample embedding, U-Net, dilated "
                      "affinity kernels, temporal accumulation and kernel; trained")
class AFNDenoiser(Denoiser):
    """A trained AFN variant. Parameters: ``checkpoint`` (required; best.pt of an ``afn`` model);
    ``kernel_size`` / ``temporal_kernel_size`` (None: as trained): taps per side at test time, changed without
    retraining (Sec. 3.6, C3.5).

    Per frame: every per-sample buffer of Sec. 3.1 (normals rotated to view space with the frame's camera), the
    per-pixel noisy mean radiance, motion and validity. Single-frame variants ignore the history.
    """

    def __init__(self, checkpoint: str | None = None, kernel_size: int | None = None,
                 temporal_kernel_size: int | None = None) -> None:
        super().__init__()
        if not checkpoint:
            raise ValueError("method 'afn' needs params.checkpoint: the path of a trained model (best.pt); in a "
                             "config, name a trained model instead with params {model: <id>}")
        for name, size in (("kernel_size", kernel_size), ("temporal_kernel_size", temporal_kernel_size)):
            if size is not None and (int(size) < 1 or int(size) % 2 == 0):
                raise ValueError(f"method 'afn': {name} must be odd and >= 1, got {size}")
        self.checkpoint = Path(checkpoint)
        self.kernel_size = int(kernel_size) if kernel_size is not None else None
        self.temporal_kernel_size = int(temporal_kernel_size) if temporal_kernel_size is not None else None
        self._model: AFNNet | None = None
        self._history: History | None = None
        self._blend: torch.Tensor | None = None

    @classmethod
    def from_model(cls, model: AFNNet, kernel_size: int | None = None,
                   temporal_kernel_size: int | None = None) -> "AFNDenoiser":
        """The method around an in-memory network (tests, benchmarks)."""
        method = cls.__new__(cls)
        Denoiser.__init__(method)
        method.checkpoint, method.kernel_size, method.temporal_kernel_size = None, kernel_size, temporal_kernel_size
        method._model, method._history, method._blend = for_inference(model), None, None
        return method

    @property
    def model(self) -> AFNNet:
        if self._model is None:
            from denoisers.training.checkpoints import load_model

            model = load_model(self.checkpoint)
            if not isinstance(model, AFNNet):
                raise TypeError(f"{self.checkpoint}: holds a {type(model).__name__}, not an AFN")
            self._model = for_inference(model).to(self.device)
        return self._model

    def _moved(self) -> None:
        if self._model is not None:
            self._model = self._model.to(self.device)
        self.reset()

    def reset(self) -> None:
        self._history = None
        self._blend = None

    def diagnostics(self) -> dict[str, torch.Tensor]:
        """``lambda`` (H, W): the temporal accumulation weight of the last frame (Eq. 3, 5; 0 at a shot's first
        frame), the paper's Fig. 5; nothing for single-frame models."""
        return {} if self._blend is None else {"lambda": self._blend}

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        camera = frame.meta.get("camera") or {}
        if "to_world" not in camera:
            raise ValueError(f"method 'afn' needs the camera (frame.meta['camera']['to_world']) to express normals "
                             f"in view space; frame {frame.index} has none")
        model = self.model
        if frame.camera_cut:
            self._history = None
        samples = {b: frame.samples[b][None] for b in SAMPLE_BUFFERS}
        features = sample_features(samples, world_to_view(camera["to_world"]).to(self.device)[None])
        temporal = model.config.temporal
        with torch.no_grad():
            step = frame_step(model, features, samples["radiance"].mean(1),
                              frame.pixel["motion"][None] if temporal else None,
                              frame.pixel["valid"][None] if temporal else None, self._history,
                              self.kernel_size, self.temporal_kernel_size)
        self._history = step.history if temporal else None
        self._blend = step.blend[0, 0] if step.blend is not None else None
        return torch.nan_to_num(step.output[0], nan=0.0, posinf=0.0, neginf=0.0)
