"""Intel Open Image Denoise on the CPU through ``pyoidn``: the production denoiser a user would pick
instead (it stands where the OptiX denoiser stands in Isik et al. 2021, Tables 2-3)."""
from __future__ import annotations

import logging

from typing import Any

import numpy as np
import torch

from denoisers.filters import check_sizes, sanitize
from denoisers.registry import Denoiser, Frame, register

#: OIDN's quality presets (the ``quality`` filter parameter).
QUALITIES = ("default", "fast", "balanced", "high")

log = logging.getLogger(__name__)


def _import_pyoidn() -> Any:
    try:
        import pyoidn
    except Exception as error:  # ImportError, or OSError when the bundled library fails to load
        raise ImportError(f"method 'oidn' needs the Python package pyoidn (Intel Open Image Denoise), "
                          f"which failed to import: {error}") from error
    return pyoidn


@register("oidn", inputs=("radiance", "albedo", "normal"),
          description="Intel Open Image Denoise (CPU, HDR, albedo + normal)")
class OpenImageDenoise(Denoiser):
    """OIDN's "RT" filter on the box-filtered radiance with albedo and normal auxiliary images, HDR mode.

    Parameters:

    - ``quality`` ("high"): OIDN quality preset, one of default / fast / balanced / high (OIDN's own
      default is high).
    - ``threads`` (0): OIDN worker threads; 0 uses torch's intra-op thread count at the first frame, so
      OIDN gets the same cores as the torch methods it is timed against.

    Inputs: mean over the frame's samples of radiance (clamped to >= 0, OIDN's HDR range), albedo
    (OIDN's convention, in [0, 1] by construction -- see ``scenegen.integrator``; clamped anyway as
    OIDN requires) and normal (world space, OIDN accepts any space). The auxiliary images are noisy
    where samples see different surfaces, so OIDN's ``cleanAux`` stays off. The device and filter are
    created once per image size, the images are shared buffers refilled per frame.
    """

    #: OIDN auxiliary images this row passes besides colour (a subset of albedo, normal; OIDN takes albedo
    #: alone, or albedo with normal).
    auxiliary: tuple[str, ...] = ("albedo", "normal")

    def __init__(self, quality: str = "high", threads: int = 0) -> None:
        super().__init__()
        if quality not in QUALITIES:
            raise ValueError(f"oidn: quality must be one of {QUALITIES}, got {quality!r}")
        if int(threads) < 0:
            raise ValueError(f"oidn: threads must be >= 0, got {threads}")
        self._pyoidn = _import_pyoidn()
        self.quality = quality
        self.threads = int(threads)
        self._device: Any = None
        self._filter: Any = None
        self._size: tuple[int, int] | None = None
        self._buffers: dict[str, np.ndarray] = {}

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, frame.samples)
        images = {"color": sanitize(frame.mean("radiance")).clamp_min_(0)}
        if "albedo" in self.auxiliary:
            images["albedo"] = sanitize(frame.mean("albedo")).clamp_(0, 1)
        if "normal" in self.auxiliary:
            images["normal"] = sanitize(frame.mean("normal")).clamp_(-1, 1)
        height, width = images["color"].shape[-2:]
        if self._size != (height, width):
            self._build(height, width)
        for name, image in images.items():
            self._buffers[name][...] = image.permute(1, 2, 0).cpu().numpy()
        self._filter.execute()
        error = self._device.get_error()
        if error is not None:
            raise RuntimeError(f"oidn: Open Image Denoise failed: {error}")
        output = torch.from_numpy(self._buffers["output"].copy()).permute(2, 0, 1).contiguous()
        return sanitize(output).to(self.device)

    def _build(self, height: int, width: int) -> None:
        """(Re)create the device, the filter and its shared (H, W, 3) float32 images."""
        pyoidn = self._pyoidn
        self.close()
        device = None
        if self.device.type == "cuda":
            # OIDN's CUDA device reads and writes the same host images (system memory) as the CPU device.
            device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CUDA)
            device.commit()
            error = device.get_error()
            if error is not None:     # this pyoidn build or driver has no CUDA device: OIDN on the CPU, said so
                log.warning("oidn: no CUDA device in pyoidn (%s); Open Image Denoise runs on the CPU", error)
                device.release()
                device = None
        if device is None:
            device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
            device.set_int("numThreads", self.threads or torch.get_num_threads())
            device.commit()
        oidn_filter = pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT)
        self._buffers = {name: np.zeros((height, width, 3), dtype=np.float32)
                         for name in ("color", *self.auxiliary, "output")}
        for name, buffer in self._buffers.items():
            oidn_filter.set_image(name, buffer, pyoidn.OIDN_FORMAT_FLOAT3)
        oidn_filter.set_bool("hdr", True)
        oidn_filter.set_int("quality", {"default": pyoidn.OIDN_QUALITY_DEFAULT, "fast": pyoidn.OIDN_QUALITY_FAST,
                                        "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                                        "high": pyoidn.OIDN_QUALITY_HIGH}[self.quality])
        oidn_filter.commit()
        error = device.get_error()
        if error is not None:
            raise RuntimeError(f"oidn: could not set up Open Image Denoise: {error}")
        self._device, self._filter, self._size = device, oidn_filter, (height, width)

    def _moved(self) -> None:
        self.close()      # the OIDN device is rebuilt for the new device type at the next frame

    def close(self) -> None:
        """Release the OIDN filter and device (they are rebuilt on the next frame if needed)."""
        if self._filter is not None:
            self._filter.release()
        if self._device is not None:
            self._device.release()
        self._device = self._filter = self._size = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the library may already be gone
            pass


@register("oidn_albedo", inputs=("radiance", "albedo"),
          description="Intel Open Image Denoise with colour and albedo only (e.g. volumes, which have no normals)")
class OpenImageDenoiseAlbedo(OpenImageDenoise):
    """OIDN's RT filter with the albedo auxiliary image only (OIDN accepts albedo without normal). On the
    volumetric clips the albedo is the single-scattering albedo at the first real collision."""

    auxiliary = ("albedo",)


@register("oidn_color", inputs=("radiance",), description="Intel Open Image Denoise on colour alone")
class OpenImageDenoiseColor(OpenImageDenoise):
    """OIDN's RT filter on the noisy colour alone (no auxiliary images), as the colour-only denoisers."""

    auxiliary = ()
