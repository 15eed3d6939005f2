"""RLS and wRLS temporal denoisers (Iglesias-Guitian, Mane and Moon 2022, §5-§6).

Every pixel and colour channel c carries a linear model  I_c ~ beta_0 + beta_1 * z_c  with predictor
p = [1, z_c] (Eq. 5), whose coefficients beta (2,) and inverse covariance P (2, 2) are updated once per
frame by recursive least squares with forgetting factor lambda (Eq. 8-11). The feature z is the
paper's temporal feature (Eq. 12): an exponentially weighted history of the noisy input whose
reprojected history is first clipped to the current 3x3 neighbourhood of the input (Karis 2014, the
paper's [26]). wRLS scales each update by w = exp(-d^2 / h^2), d = |I - z| / (min(|I|, |z|) + eps)
(Eq. 13-14), so outliers barely move the models; RLS is the same filter with w = 1 (the paper's
ablation, Fig. 8-9). Models and feature are carried to the next frame by reprojection with the motion
vectors and reset where reprojection is not trustworthy. The output blends, per pixel i, the predictions
p_i . beta_k of the models k in the 5x5 window around i with bilateral weights (§5.3, "spatio-temporal
denoising").

All pixels are updated at once: the 2x2 Sherman-Morrison update is written out in closed form on
(3, H, W) tensors (no per-pixel loops). Radiance is linear HDR throughout (§6: "we perform the denoising
in the original HDR space").

Choices the paper leaves open (documented here and on each parameter):
- predictor: the feature image z is RGB (§5.3, "z_j in R^3"); the model of channel c uses its own
  channel, p = [1, z_c], and P is 2x2 per pixel and channel (the paper denoises channels independently);
- initial model: beta = [0, 1] (predict the feature) and P = diag(delta_0, delta_1 / m^2), m the pixel's
  feature magnitude, i.e. P = diag(delta_0, delta_1) on the intensity-normalised regression, so the
  prior does not depend on the scene's radiance scale. delta_1 is small on purpose: z contains the
  current input (weight 1 - alpha), so the least-squares slope of the noisy input on z is biased above 1
  by the shared noise (about 1.75 on a static pixel with alpha = 0.75) and would amplify noise; the tight
  prior keeps it near 1 unless the data insist (on our own small Mitsuba test renders at 1-4 spp,
  delta_1 = 1e-3 beats 1e-2 by 0.05-0.3 dB PSNR and 1e-1 by up to 0.6 dB; much smaller values turn the
  model into an intercept-only one);
- norms |.| in Eq. 13 are Euclidean norms of RGB vectors (one weight per pixel);
- neighbourhood clamping clips the RGB history towards the centre of the 3x3 min/max box (Karis's
  "clip", which moves all three channels together and so avoids the colour shifts the paper mentions);
- bilinear reprojection of feature, coefficients and P (denoisers.filters.warp_previous; a convex blend
  of positive-definite matrices stays positive definite);
- bilateral blending weight: Gaussian in pixel distance times exp(-d^2 / h_b^2) with the relative
  colour distance d of Eq. 13 measured between the features of the two pixels;
- the output is clamped to >= 0 (radiance is non-negative; a linear model may undershoot).

Inputs are sanitised (NaN/Inf -> 0, magnitudes clamped, denoisers.filters.sanitize), so the output is
finite for any input.

Known behaviour: at 1-2 spp many pixels receive exactly-zero estimates; Eq. 13 gives them d = |z| / eps
and a weight ~0, so wRLS fits its models to the non-zero estimates only and brightens dark, sparse
regions (mean output / reference about 1.15 at 1 spp, 1.03 at 4 spp on our renders). The paper's
pipeline feeds the denoiser Gaussian-filtered estimates, which rarely are exactly zero; ``prefilter``
reproduces that step.
"""
from __future__ import annotations

from typing import ClassVar

import torch
import torch.nn.functional as F

from denoisers.filters import MIN_LOG_WEIGHT, gaussian_blur_3x3, sanitize, warp_previous
from denoisers.registry import Denoiser, Frame, register


def _box_min_max(image: torch.Tensor, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-channel min and max of ``image`` (C, H, W) over the (2 radius + 1)^2 window, both (C, H, W).

    Separable shifted-slice min/max on a replicate-padded copy (padding repeats in-window values, so
    it does not change the result); much faster than max_pool2d on the CPU.
    """
    height, width = image.shape[-2:]
    size = 2 * radius + 1
    padded = F.pad(image[None], (radius,) * 4, mode="replicate")[0]
    row_max, row_min = padded[..., :width], padded[..., :width]
    for shift in range(1, size):
        row_max = torch.maximum(row_max, padded[..., shift:shift + width])
        row_min = torch.minimum(row_min, padded[..., shift:shift + width])
    box_max, box_min = row_max[..., :height, :], row_min[..., :height, :]
    for shift in range(1, size):
        box_max = torch.maximum(box_max, row_max[..., shift:shift + height, :])
        box_min = torch.minimum(box_min, row_min[..., shift:shift + height, :])
    return box_min, box_max


def clip_to_neighbourhood(history: torch.Tensor, current: torch.Tensor, radius: int = 1) -> torch.Tensor:
    """Clip the RGB ``history`` (3, H, W) into the min/max box of ``current`` (3, H, W) over the
    (2 radius + 1)^2 neighbourhood, moving it along the line towards the box centre (Karis 2014)."""
    box_min, box_max = _box_min_max(current, radius)
    centre = 0.5 * (box_max + box_min)
    half_extent = 0.5 * (box_max - box_min)
    offset = history - centre
    # How far outside the box the history is, in units of the box half-size, along its worst channel;
    # the tiny floor makes a flat neighbourhood (zero-size box) pull the history onto the box.
    excess = offset.abs() / half_extent.clamp_min(1e-30)
    worst = torch.maximum(torch.maximum(excess[0], excess[1]), excess[2])
    return centre + offset / worst.clamp_min(1.0)


def _squared_rgb_norm(rgb: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean norm over the 3 channels of (3, ...) -> (...). (Explicit sums: a reduction over
    the leading dim with torch.linalg.vector_norm is an order of magnitude slower on the CPU.)"""
    return rgb[0] * rgb[0] + rgb[1] * rgb[1] + rgb[2] * rgb[2]


def _rgb_norm(rgb: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the 3 channels of (3, ...) -> (...)."""
    return _squared_rgb_norm(rgb).sqrt_()


def squared_relative_distance(a: torch.Tensor, b: torch.Tensor, epsilon: float,
                              norm_a: torch.Tensor | None = None, norm_b: torch.Tensor | None = None) -> torch.Tensor:
    """Square of Eq. 13's d = |a - b| / (min(|a|, |b|) + eps) for RGB images a, b (3, H, W) -> (H, W).

    norm_a, norm_b: |a|, |b| if already known.
    """
    norm_a = _rgb_norm(a) if norm_a is None else norm_a
    norm_b = _rgb_norm(b) if norm_b is None else norm_b
    return _squared_rgb_norm(a - b).div_(torch.minimum(norm_a, norm_b).add_(epsilon).square_())


def rls_update(beta: torch.Tensor, cov: torch.Tensor, feature: torch.Tensor, target: torch.Tensor,
               weight: torch.Tensor, forgetting: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One (weighted) RLS step for independent scalar models with predictor p = [1, z] (Eq. 8-11, 14).

    beta: (2, ...) coefficients (beta_0, beta_1); cov: (3, ...) the symmetric inverse covariance P as
    (P00, P01, P11); feature z, target I (the noisy estimate) and weight w: (...) or broadcastable.
    Eq. 14 writes the gain as P p / (lambda / w + p P p); it is evaluated as w P p / (lambda + w p P p),
    equal for w > 0 and a zero gain (no update, P <- P / lambda) for w = 0.
    Returns the new (beta, cov): the minimiser of
    sum_s lambda^(t-s) w_s (I_s - p_s beta)^2 + lambda^t (beta - beta_init)^T P_init^-1 (beta - beta_init).
    """
    p00, p01, p11 = cov[0], cov[1], cov[2]
    gain0 = p00 + p01 * feature                      # g = P p
    gain1 = p01 + p11 * feature
    scale = weight / (forgetting + weight * (gain0 + feature * gain1))
    k0, k1 = scale * gain0, scale * gain1            # q = w P p / (lambda + w p P p)
    error = target - (beta[0] + beta[1] * feature)   # a-priori error (Eq. 8)
    new_beta = torch.stack((beta[0] + k0 * error, beta[1] + k1 * error))     # Eq. 9
    # Eq. 11: P <- (P - q p P) / lambda, with q p P = k g^T (symmetric, k is parallel to g).
    inv_forgetting = 1.0 / forgetting
    n00 = ((p00 - k0 * gain0) * inv_forgetting).clamp_min(1e-30)
    n11 = ((p11 - k1 * gain1) * inv_forgetting).clamp_min(1e-30)
    n01 = (p01 - k0 * gain1) * inv_forgetting
    # Rounding may leave P marginally indefinite: keep |P01| <= sqrt(P00 P11).
    bound = torch.sqrt(n00 * n11)
    n01 = torch.minimum(torch.maximum(n01, -bound), bound)
    return new_beta, torch.stack((n00, n01, n11))


class _RecursiveLeastSquares(Denoiser):
    """Shared implementation of RLS (``weighted = False``) and wRLS (``weighted = True``)."""

    weighted: ClassVar[bool]

    def __init__(self, forgetting_factor: float = 0.998, feature_alpha: float = 0.75, bandwidth: float = 0.75,
                 epsilon: float = 1e-4, clamp_radius: int = 1, blend_radius: int = 2, blend_sigma: float = 2.0,
                 blend_bandwidth: float = 0.75, prior_intercept: float = 1.0, prior_slope: float = 1e-3,
                 magnitude_floor: float = 0.01, prefilter: bool = False) -> None:
        """Parameters (source in brackets).

        forgetting_factor: lambda of Eq. 10-11 [paper §5.2, 0.998].
        feature_alpha: alpha of Eq. 12, weight of the clipped history in the feature [paper §6, 0.75].
        bandwidth: h of Eq. 13 [paper §5.3, 0.75]; wRLS only.
        epsilon: eps of Eq. 13, radiance units [paper: "a very small number"; ours 1e-4].
        clamp_radius: neighbourhood of the clipping Psi in Eq. 12, 1 = 3x3 [Karis 2014, the paper's [26]].
        blend_radius: spatial blending window, 2 = 5x5 [paper §5.3]; 0 turns blending off.
        blend_sigma: std of the blending weight's spatial Gaussian, pixels [ours].
        blend_bandwidth: range bandwidth of the blending weight on Eq. 13's relative distance between the
            two pixels' features [ours].
        prior_intercept, prior_slope: initial P = diag(prior_intercept, prior_slope / m^2), m^2 = z^2 +
            (magnitude_floor * mean input radiance)^2, with beta = [0, 1] [ours; the paper states neither].
        prefilter: apply a 3x3 Gaussian (binomial) pixel reconstruction filter to the noisy estimate first,
            as the paper's pipeline does before its denoiser [§4 and §6, "separable Gaussian kernel"; width
            ours]. Off by default: our renderer's pixel filter is the box and the references are
            box-filtered, so the prefilter adds a blur the reference does not have.
        """
        super().__init__()
        name = self.info.name
        if not 0 < forgetting_factor <= 1:
            raise ValueError(f"{name}: forgetting_factor must be in (0, 1], got {forgetting_factor}")
        if not 0 <= feature_alpha < 1:
            raise ValueError(f"{name}: feature_alpha must be in [0, 1), got {feature_alpha}")
        if min(bandwidth, blend_bandwidth, blend_sigma, epsilon, prior_intercept, prior_slope) <= 0:
            raise ValueError(f"{name}: bandwidths, blend_sigma, epsilon and the priors must be > 0")
        if clamp_radius < 0 or blend_radius < 0 or magnitude_floor < 0:
            raise ValueError(f"{name}: radii and magnitude_floor must be >= 0")
        self.forgetting_factor = float(forgetting_factor)
        self.feature_alpha = float(feature_alpha)
        self.bandwidth = float(bandwidth)
        self.epsilon = float(epsilon)
        self.clamp_radius = int(clamp_radius)
        self.blend_radius = int(blend_radius)
        self.blend_sigma = float(blend_sigma)
        self.blend_bandwidth = float(blend_bandwidth)
        self.prior_intercept = float(prior_intercept)
        self.prior_slope = float(prior_slope)
        self.magnitude_floor = float(magnitude_floor)
        self.prefilter = bool(prefilter)
        self.reset()

    def reset(self) -> None:
        # Carried state, float32: one (18, H, W) tensor so that reprojection is a single warp:
        # feature z (3), beta_0 (3), beta_1 (3), P00 (3), P01 (3), P11 (3), each per colour channel.
        self._state: torch.Tensor | None = None

    # -- per-frame steps -------------------------------------------------------------------------------

    def _history_mask(self, frame: Frame, height: int, width: int) -> torch.Tensor | None:
        """(H, W) bool where the reprojected state may be used, or None where no pixel has history."""
        if self._state is None or frame.camera_cut:
            return None
        if self._state.shape[-2:] != (height, width):
            raise ValueError(f"{self.info.name}: frame {frame.index} is {height}x{width} but the previous "
                             f"frame was {self._state.shape[-2]}x{self._state.shape[-1]}; call reset() "
                             f"between clips")
        valid = frame.pixel["valid"]
        if valid.shape[-2:] != (height, width) or valid.numel() != height * width:
            raise ValueError(f"{self.info.name}: 'valid' is {tuple(valid.shape)}, radiance is {height}x{width}")
        mask = valid.reshape(height, width) > 0.5
        return mask if bool(mask.any()) else None

    def _reprojected_state(self, frame: Frame) -> torch.Tensor:
        """The previous frame's (18, H, W) state, bilinearly sampled at pixel centre + motion."""
        height, width = self._state.shape[-2:]
        motion = frame.pixel["motion"]
        if motion.shape != (2, height, width):
            raise ValueError(f"{self.info.name}: 'motion' is {tuple(motion.shape)}, expected (2, {height}, {width})")
        motion = torch.nan_to_num(motion.to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if not bool(motion.any()):
            return self._state
        return warp_previous(self._state, motion)

    def _blend(self, beta: torch.Tensor, feature: torch.Tensor) -> torch.Tensor:
        """(3, H, W) output: per pixel i, the bilateral average over the window of the predictions
        p_i . beta_k = beta_0,k + beta_1,k z_i of its neighbours' models k (§5.3).

        beta: (6, H, W) = (beta_0 RGB, beta_1 RGB); feature z: (3, H, W).
        """
        radius = self.blend_radius
        if radius == 0:
            return beta[:3] + beta[3:] * feature
        height, width = feature.shape[-2:]
        padded_height, padded_width = height + 2 * radius, width + 2 * radius
        padded_feature = F.pad(feature[None], (radius,) * 4, mode="replicate")[0]
        padded_beta = F.pad(beta[None], (radius,) * 4, mode="replicate")[0]
        padded_norm = _rgb_norm(padded_feature)
        inv_range = 1.0 / self.blend_bandwidth ** 2
        inv_spatial = 1.0 / (2.0 * self.blend_sigma ** 2)
        accumulated = beta.clone()                              # centre tap, weight 1
        weight_sum = torch.ones(height, width, dtype=beta.dtype)
        # The weight is symmetric in (i, k), so one map per offset pair (o, -o) serves both taps.
        for dy in range(0, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx <= 0:
                    continue
                # pair_weight[y, x] = weight between padded pixels (y, x) and (y + dy, x + dx).
                rows = slice(0, padded_height - dy)
                cols = slice(max(0, -dx), padded_width - max(0, dx))
                rows_k = slice(dy, padded_height)
                cols_k = slice(max(0, dx), padded_width - max(0, -dx))
                distance_sq = squared_relative_distance(
                    padded_feature[:, rows, cols], padded_feature[:, rows_k, cols_k], self.epsilon,
                    padded_norm[rows, cols], padded_norm[rows_k, cols_k])
                exponent = distance_sq.mul_(-inv_range).sub_((dx * dx + dy * dy) * inv_spatial)
                pair_weight = torch.exp(exponent.clamp_min_(MIN_LOG_WEIGHT))
                # Tap +o at output pixel i = (y, x): pair (i, i + o), at pair_weight[y + r, x + r - max(0, -dx)].
                y0, x0 = radius, radius - max(0, -dx)
                forward = pair_weight[y0:y0 + height, x0:x0 + width]
                accumulated.addcmul_(forward, padded_beta[:, radius + dy:radius + dy + height,
                                                          radius + dx:radius + dx + width])
                weight_sum += forward
                # Tap -o: pair (i - o, i), at pair_weight[y + r - dy, x + r - dx - max(0, -dx)].
                y1, x1 = radius - dy, radius - dx - max(0, -dx)
                backward = pair_weight[y1:y1 + height, x1:x1 + width]
                accumulated.addcmul_(backward, padded_beta[:, radius - dy:radius - dy + height,
                                                           radius - dx:radius - dx + width])
                weight_sum += backward
        accumulated /= weight_sum
        return accumulated[:3] + accumulated[3:] * feature

    def denoise(self, frame: Frame) -> torch.Tensor:
        noisy = sanitize(frame.mean("radiance"))
        if self.prefilter:
            noisy = gaussian_blur_3x3(noisy)
        channels, height, width = noisy.shape
        if channels != 3:
            raise ValueError(f"{self.info.name}: radiance must have 3 channels, got {channels}")
        history_ok = self._history_mask(frame, height, width)

        # Initial models (used where there is no history): beta = [0, 1], P = diag(d0, d1 / m^2).
        floor = self.magnitude_floor * float(noisy.abs().mean()) + 1e-12
        if history_ok is None:
            feature = noisy
            beta = torch.cat((torch.zeros_like(noisy), torch.ones_like(noisy)))
            cov = torch.cat((torch.full_like(noisy, self.prior_intercept), torch.zeros_like(noisy),
                             self.prior_slope / (noisy * noisy + floor * floor)))
        else:
            previous = self._reprojected_state(frame)
            history = clip_to_neighbourhood(previous[:3], noisy, self.clamp_radius)
            keep = history_ok.to(noisy.dtype)
            # Eq. 12; without history z = I.
            feature = torch.lerp(noisy, history, self.feature_alpha * keep)
            if bool(history_ok.all()):
                models = previous[3:]
            else:
                init = torch.cat((torch.zeros_like(noisy), torch.ones_like(noisy),
                                  torch.full_like(noisy, self.prior_intercept), torch.zeros_like(noisy),
                                  self.prior_slope / (feature * feature + floor * floor)))
                # keep is exactly 0 or 1, so the blend selects (torch.where is far slower here).
                models = torch.lerp(init, previous[3:], keep)
            beta, cov = models[:6], models[6:]

        if self.weighted:
            distance_sq = squared_relative_distance(noisy, feature, self.epsilon)
            # Eq. 13
            weight = torch.exp(distance_sq.mul_(-1.0 / self.bandwidth ** 2).clamp_min_(MIN_LOG_WEIGHT))
        else:
            weight = torch.ones((), dtype=noisy.dtype)
        new_beta, new_cov = rls_update(beta.view(2, 3, height, width), cov.view(3, 3, height, width),
                                       feature, noisy, weight, self.forgetting_factor)
        new_beta, new_cov = new_beta.view(6, height, width), new_cov.view(9, height, width)
        self._state = torch.cat((feature, new_beta, new_cov))
        output = self._blend(new_beta, feature).clamp_min_(0.0)
        return torch.nan_to_num_(output, nan=0.0, posinf=0.0, neginf=0.0)


@register("wrls", inputs=("radiance",), pixel_inputs=("motion", "valid"), temporal=True,
          description="weighted recursive least squares with a temporal feature (Iglesias-Guitian et al. 2022)")
class WeightedRLS(_RecursiveLeastSquares):
    """wRLS (Iglesias-Guitian et al. 2022): per-pixel RLS linear models on a temporal feature, outlier
    weights from Eq. 13, 5x5 bilateral blending of the models' predictions."""

    weighted = True


@register("rls", inputs=("radiance",), pixel_inputs=("motion", "valid"), temporal=True,
          description="recursive least squares with a temporal feature (wRLS without weights)")
class RLS(_RecursiveLeastSquares):
    """RLS: wRLS with every weight w = 1 (the paper's ablation, Fig. 8-9)."""

    weighted = False

    def __init__(self, forgetting_factor: float = 0.998, feature_alpha: float = 0.75, epsilon: float = 1e-4,
                 clamp_radius: int = 1, blend_radius: int = 2, blend_sigma: float = 2.0,
                 blend_bandwidth: float = 0.75, prior_intercept: float = 1.0, prior_slope: float = 1e-3,
                 magnitude_floor: float = 0.01, prefilter: bool = False) -> None:
        """Same parameters as wRLS except ``bandwidth`` (there are no weights)."""
        super().__init__(forgetting_factor=forgetting_factor, feature_alpha=feature_alpha, epsilon=epsilon,
                         clamp_radius=clamp_radius, blend_radius=blend_radius, blend_sigma=blend_sigma,
                         blend_bandwidth=blend_bandwidth, prior_intercept=prior_intercept,
                         prior_slope=prior_slope, magnitude_floor=magnitude_floor, prefilter=prefilter)
