"""The recurrent denoising autoencoder (Chaitanya et al. 2017) as an evaluation method: a trained network
(``denoisers.nets.rae``) streamed frame by frame with its recurrent state carried between frames."""
from __future__ import annotations

from pathlib import Path

import torch

from denoisers.filters import check_sizes
from denoisers.nets import for_inference
from denoisers.nets.rae import RecurrentAutoencoder, State
from denoisers.nets.rae_task import (COLOR_INPUT_BUFFERS, GBUFFER_FEATURE_BUFFERS, INPUT_BUFFERS, buffer_means,
                                     check_color_only, decode_color, gbuffer_features, prepare_inputs)
from denoisers.nets.view import world_to_view
from denoisers.registry import Denoiser, Frame, register




@register("rae_samples", inputs=INPUT_BUFFERS, trainable=True, temporal=True,
          description="the RAE with its albedo and features averaged over the frame's samples (one jittered sample "
                      "per pixel at 1 spp) instead of the paper's G-buffer; trained")
class RecurrentAutoencoderDenoiser(Denoiser):
    """A trained RAE applied to a stream of frames.

    Parameters:

    - ``checkpoint`` (required): path of a model or training checkpoint written by
      ``denoisers.training.loop`` (``best.pt``); the architecture and input encoding are read from it.
      The file is read at the first frame, so building the method (e.g. to plan an evaluation before
      the model is trained) only checks that a path is given.
    - ``reset_state_every_frame`` (False): start every frame from a zero recurrent state (the C1.5
      ablation: the same weights without temporal memory).

    Per frame: per-pixel means over the frame's samples of radiance, albedo, normal, depth and
    roughness; normals are rotated into view space with the frame's camera (``frame.meta['camera']
    ['to_world']``, written by the renderer into every frame's sidecar); colour is divided by
    max(albedo, floor) and raised to the power 0.2; the network output is raised to the power 5 and
    multiplied by the same divisor. The state is also dropped at a camera cut (training sequences never
    cross one).
    """

    def __init__(self, checkpoint: str | None = None, reset_state_every_frame: bool = False) -> None:
        super().__init__()
        if not checkpoint:
            raise ValueError(f"method {self.info.name!r} needs params.checkpoint: the path of a trained RAE model "
                             "(best.pt written by the trainer); in a config, name a trained model instead with "
                             "params {model: <id in training.models>}; no checkpoint was given")
        self.checkpoint = Path(checkpoint)
        self.reset_state_every_frame = bool(reset_state_every_frame)
        self._model: RecurrentAutoencoder | None = None
        self._state: State | None = None

    @classmethod
    def from_model(cls, model: RecurrentAutoencoder, reset_state_every_frame: bool = False
                   ) -> "RecurrentAutoencoderDenoiser":
        """The method around an in-memory network (tests, benchmarks) instead of a checkpoint file. Puts
        ``model`` in eval mode with its weights in channels-last layout (in place; values unchanged)."""
        method = cls.__new__(cls)
        Denoiser.__init__(method)
        method.checkpoint = None
        method.reset_state_every_frame = bool(reset_state_every_frame)
        method.check_model(model, f"method {cls.info.name!r}")
        method._model = for_inference(model)
        method._state = None
        return method

    @property
    def model(self) -> RecurrentAutoencoder:
        if self._model is None:
            from denoisers.training.checkpoints import load_model

            model = load_model(self.checkpoint)
            if not isinstance(model, RecurrentAutoencoder):
                raise TypeError(f"{self.checkpoint}: holds a {type(model).__name__}, not an RAE")
            self.check_model(model, f"method {self.info.name!r} ({self.checkpoint})")
            self._model = for_inference(model).to(self.device)
        return self._model

    def check_model(self, model: RecurrentAutoencoder, where: str) -> None:
        """ValueError unless ``model`` reads its features where this method gives them (the samples)."""
        if model.config.features_from != "samples":
            raise ValueError(f"{where}: the model reads its features from the {model.config.features_from} "
                             "(net features_from); evaluate it with method 'rae'")

    def features(self, frame: Frame) -> dict[str, torch.Tensor]:
        """Per-pixel radiance, albedo, normal, depth and roughness (C, H, W) of ``frame``: means over its samples."""
        return buffer_means(frame.samples, self.info.inputs, sample_dim=0)

    def _moved(self) -> None:
        if self._model is not None:
            self._model = self._model.to(self.device)
        self.reset()

    def reset(self) -> None:
        self._state = None

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        camera = frame.meta.get("camera") or {}
        if "to_world" not in camera:
            raise ValueError(f"method 'rae' needs the camera (frame.meta['camera']['to_world']) to express "
                             f"normals in view space; frame {frame.index} has none")
        model = self.model
        if self.reset_state_every_frame or frame.camera_cut:
            self._state = None
        means = self.features(frame)
        rotation = world_to_view(camera["to_world"]).to(self.device)
        x, divisor = prepare_inputs(model.config, means["radiance"], means["albedo"], means["normal"],
                                    means["depth"], means["roughness"], rotation)
        out, self._state = model.inference_step(x[None], self._state)
        return torch.nan_to_num(decode_color(out[0], divisor, model.config.exponent), nan=0.0, posinf=0.0,
                                neginf=0.0)


@register("rae_color", inputs=COLOR_INPUT_BUFFERS, trainable=True, temporal=True,
          description="the RAE on colour alone (trained colour-only, e.g. on volumetric clips; Iglesias-Guitian 2022)")
class ColorRecurrentAutoencoderDenoiser(RecurrentAutoencoderDenoiser):
    """The RAE reading the noisy colour alone: its model must be colour-only (net demodulate false, features []),
    as Iglesias-Guitian et al. 2022 retrain it for volumes, whose clips have no normals. Parameters as
    ``rae_samples``."""

    def check_model(self, model: RecurrentAutoencoder, where: str) -> None:
        check_color_only(model.config, where)


@register("rae", inputs=COLOR_INPUT_BUFFERS, pixel_inputs=GBUFFER_FEATURE_BUFFERS, trainable=True, temporal=True,
          description="recurrent denoising autoencoder (Chaitanya et al. 2017), trained; albedo and features from "
                      "the pixel-centre G-buffer, as the paper's rasterised G-buffer (§3.1-3.2)")
class GBufferRecurrentAutoencoderDenoiser(RecurrentAutoencoderDenoiser):
    """The RAE reading the noisy colour per sample and its albedo, normal, depth and roughness from the frame's
    pixel-centre G-buffer (noise-free at any spp; ``gbuffer.*`` per-pixel buffers): its model must have net
    features_from gbuffer (trained with task ``rae``). Parameters as ``rae_samples``."""

    def check_model(self, model: RecurrentAutoencoder, where: str) -> None:
        if model.config.features_from != "gbuffer":
            raise ValueError(f"{where}: method 'rae' needs a model trained on G-buffer features (net features_from "
                             f"gbuffer, task rae); this one reads {model.config.features_from}: use method "
                             "'rae_samples'")

    def features(self, frame: Frame) -> dict[str, torch.Tensor]:
        return {**super().features(frame), **gbuffer_features(frame.pixel)}
