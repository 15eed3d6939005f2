"""The RAE's inputs (§3.2, §4.4 of Chaitanya et al. 2017) and its training task; the network is
:mod:`denoisers.nets.rae`.

Per frame the network reads [colour^0.2, view-space normal x y, depth, roughness] (the configured subset),
colour demodulated by max(albedo, albedo_floor) unless ``demodulate`` is off; the albedo and features are the
per-pixel means of the frame's samples or its pixel-centre G-buffer (``RAEConfig.features_from``).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from denoisers.filters import sanitize
from denoisers.losses import RAE_LOSS_WEIGHTS, rae_loss
from denoisers.nets.rae import DEPTH_ENCODINGS, RAEConfig, RecurrentAutoencoder

#: Per-pixel G-buffer buffers a ``features_from: gbuffer`` RAE reads (scenegen.channels.PIXEL_BUFFERS names).
GBUFFER_FEATURE_BUFFERS: tuple[str, ...] = ("gbuffer.albedo", "gbuffer.normal", "gbuffer.depth", "gbuffer.roughness")


def encode_color(linear: torch.Tensor, divisor: torch.Tensor, exponent: float) -> torch.Tensor:
    """(linear / divisor)^exponent with non-finite values -> 0 and negatives clamped to 0."""
    return (sanitize(linear) / divisor).clamp_min(0).pow(exponent)


def decode_color(encoded: torch.Tensor, divisor: torch.Tensor, exponent: float) -> torch.Tensor:
    """Inverse of :func:`encode_color`: max(encoded, 0)^(1/exponent) * divisor (linear HDR radiance)."""
    return encoded.clamp_min(0).pow(1.0 / exponent) * divisor


def prepare_inputs(config: RAEConfig, radiance: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,
                   depth: torch.Tensor, roughness: torch.Tensor,
                   view_rotation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input and demodulation divisor from per-pixel means over the samples.

    radiance, albedo, normal (world space): (..., 3, H, W); depth, roughness: (..., 1, H, W), metres
    and linear alpha; view_rotation: (..., 3, 3) from :func:`world_to_view` (leading dims as the
    images'). Returns x (..., in_channels, H, W) = [colour^0.2, normal_view x y, depth, roughness]
    (the configured subset) and divisor (..., 3, H, W) = max(albedo, albedo_floor), or ones when
    ``config.demodulate`` is off. Non-finite inputs become 0.
    """
    divisor = sanitize(albedo).clamp_min(config.albedo_floor) if config.demodulate else torch.ones_like(radiance)
    channels = [encode_color(radiance, divisor, config.exponent)]
    for feature in config.features:
        if feature == "normal":
            rotation = sanitize(view_rotation)[..., :2, :]
            channels.append(torch.einsum("...ij,...jhw->...ihw", rotation, sanitize(normal)))
        elif feature == "depth":
            channels.append(DEPTH_ENCODINGS[config.depth_encoding](sanitize(depth)))
        else:
            channels.append(sanitize(roughness))
    return torch.cat(channels, dim=-3), divisor


# ----------------------------------------------------------------------------------- training task
#: Per-sample buffers the RAE reads.
INPUT_BUFFERS: tuple[str, ...] = ("radiance", "albedo", "normal", "depth", "roughness")
#: Per-sample buffers of the colour-only RAE (``rae_color``; Iglesias-Guitian et al. 2022 train it on volumes).
COLOR_INPUT_BUFFERS: tuple[str, ...] = ("radiance",)
_ZERO_CHANNELS = {"albedo": 3, "normal": 3, "depth": 1, "roughness": 1}


def check_color_only(config: RAEConfig, where: str) -> None:
    """ValueError unless ``config`` reads colour alone (no demodulation, no auxiliary features)."""
    if config.demodulate or config.features:
        raise ValueError(f"{where}: a colour-only RAE needs net {{demodulate: false, features: []}}, got demodulate "
                         f"{config.demodulate}, features {list(config.features)}")


def gbuffer_features(pixel: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """{albedo, normal, depth, roughness} of :func:`prepare_inputs` from the per-pixel G-buffer buffers
    ``gbuffer.*`` ((..., C, H, W) each); KeyError naming a missing one."""
    missing = [name for name in GBUFFER_FEATURE_BUFFERS if name not in pixel]
    if missing:
        raise KeyError(f"rae (features_from gbuffer): per-pixel buffers {missing} are missing; render with a G-buffer "
                       "pass that stores them (scenegen.channels.PIXEL_BUFFERS)")
    return {name.split(".", 1)[1]: pixel[name] for name in GBUFFER_FEATURE_BUFFERS}


def buffer_means(samples: Mapping[str, torch.Tensor], buffers: tuple[str, ...], sample_dim: int
                 ) -> dict[str, torch.Tensor]:
    """Per-pixel means over ``sample_dim`` of every RAE input buffer; buffers outside ``buffers`` (the colour-only
    RAE's) are zeros of their channel count, which a colour-only config never reads."""
    means = {b: samples[b].mean(dim=sample_dim) for b in buffers}
    radiance = means["radiance"]
    for name, channels in _ZERO_CHANNELS.items():
        if name not in means:
            shape = (*radiance.shape[:-3], channels, *radiance.shape[-2:])
            means[name] = torch.zeros(shape, dtype=radiance.dtype)
    return means


@dataclass
class RAETask:
    """How the trainer (``denoisers.training.loop``) trains an RAE on ``denoisers.training.data`` batches.

    A batch holds per-sample buffers (N, T, S, C, H, W) of :data:`INPUT_BUFFERS` (only radiance with
    ``config.features_from == "gbuffer"``, which reads the per-pixel (N, T, C, H, W)
    :data:`GBUFFER_FEATURE_BUFFERS` instead), ``reference.radiance`` (N, T, 3, H, W) and ``world_to_view``
    (N, T, 3, 3). The target is the reference demodulated by the same divisor as the input (the frame's mean
    sample albedo, or its G-buffer albedo), raised to the power 0.2; the loss is
    :func:`denoisers.losses.rae_loss`.
    """

    config: RAEConfig = field(default_factory=RAEConfig)
    loss_weights: dict[str, float] = field(default_factory=lambda: dict(RAE_LOSS_WEIGHTS))

    name: str = "rae_samples"
    buffers: tuple[str, ...] = INPUT_BUFFERS        # COLOR_INPUT_BUFFERS for the colour-only and G-buffer RAEs

    def __post_init__(self) -> None:
        if self.config.features_from == "gbuffer":
            if self.buffers != COLOR_INPUT_BUFFERS:
                raise ValueError(f"{self.name}: an RAE with features_from gbuffer reads radiance alone per sample, "
                                 f"got {list(self.buffers)}")
        elif self.buffers != INPUT_BUFFERS:
            check_color_only(self.config, self.name)

    def build_model(self) -> RecurrentAutoencoder:
        return RecurrentAutoencoder(self.config)

    def net_spec(self) -> dict[str, Any]:
        return {"name": RecurrentAutoencoder.NET_NAME, "config": self.config.to_dict()}

    def describe(self) -> dict[str, Any]:
        """Everything that changes what training computes (part of the checkpoint's fingerprint)."""
        return {"task": self.name, "net": self.net_spec(), "loss_weights": dict(self.loss_weights)}

    def inputs(self, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """(x (N, T, in_channels, H, W), divisor (N, T, 3, H, W)) of a batch."""
        means = buffer_means(batch, self.buffers, sample_dim=2)
        if self.config.features_from == "gbuffer":
            means.update(gbuffer_features(batch))
        return prepare_inputs(self.config, means["radiance"], means["albedo"], means["normal"], means["depth"],
                              means["roughness"], batch["world_to_view"])

    def loss(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        x, divisor = self.inputs(batch)
        target = encode_color(batch["reference.radiance"], divisor, self.config.exponent)
        pred, _ = model(x)
        total, terms = rae_loss(pred, target, self.loss_weights)
        return total, {name: float(value) for name, value in terms.items()}

    def predict(self, model: nn.Module, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """(N, T, 3, H, W) linear HDR radiance of the model on a batch (state carried through each sequence)."""
        x, divisor = self.inputs(batch)
        pred, _ = model(x)
        return decode_color(pred, divisor, self.config.exponent)
