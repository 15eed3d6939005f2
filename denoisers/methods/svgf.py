"""Spatiotemporal variance-guided filtering (Schied et al. 2017, HPG), the SVGF baseline of
Hasselgren et al. 2020 and Iglesias-Guitian et al. 2022."""
from __future__ import annotations

import math

import torch

from denoisers import native
from denoisers.filters import (B3_SPLINE, MIN_LOG2_WEIGHT, MIN_LOG_WEIGHT, REC709_LUMINANCE, PairWorkspace,
                               bilinear_footprint, check_sizes, gaussian_blur_3x3, luminance, normalize_vectors,
                               revisited_next_step, sanitize)
from denoisers.methods.svgf_terms import (DEPTH_EPSILON_RELATIVE, LUMINANCE_EPSILON, MAX_HISTORY,
                                          MIN_REPROJECTION_WEIGHT, NORMAL_COSINE_FLOOR, SPARSE_VARIANCE_FRACTION,
                                          GeometryTerms, History, cosine_floor, depth_gradient, moment_variance)
from denoisers.registry import Denoiser, Frame, register


@register("svgf", inputs=("radiance", "albedo", "normal", "depth"),
          pixel_inputs=("motion", "valid", "gbuffer.depth", "gbuffer.normal"), temporal=True,
          description="spatiotemporal variance-guided filtering (Schied et al. 2017)")
class SVGF(Denoiser):
    """Spatiotemporal variance-guided filtering, frame by frame with its own history.

    Per frame (Schied et al. 2017): (1) demodulate the albedo, illumination = radiance /
    max(albedo, ``albedo_epsilon``); (2) reproject the previous integrated illumination and luminance
    moments with the motion vectors -- bilinear, keeping only taps whose pixel-centre G-buffer depth and
    normal agree with this pixel's (and only where the renderer's ``valid`` mask is set) -- and blend
    with exponential moving averages; (3) variance = m2 - m1^2 from the integrated moments, or from a
    7x7 depth/normal-weighted spatial estimate where the history is shorter than 4 frames; (4)
    ``iterations`` variance-guided a-trous passes (taps 2^i apart) with weights
    w = exp(-|z_p - z_q| / (sigma_z |grad z . (p - q)| + eps)) * max(0, n_p . n_q)^sigma_n
        * exp(-|l_p - l_q| / (sigma_l sqrt(g3x3(Var(l_p))) + eps)),
    the variance filtered alongside with squared weights; the first pass's output becomes the colour
    history; (5) remodulate with the albedo. The paper's final TAA pass is not applied (no method in the
    harness gets one). The paper's 3x3 search for a consistent history when all bilinear taps fail is
    not done either: such pixels restart their history.

    Parameters and their sources (paper = Schied et al. 2017; issue = the issue text of this harness):

    - ``alpha_color`` (0.2), ``alpha_moments`` (0.2): EMA weights of the new frame (paper). While the
      history is n frames long the weight is max(alpha, 1/n) -- a plain mean of the frames seen so far,
      the ramp for short histories the issue asks for.
    - ``sigma_luminance`` (4), ``sigma_normal`` (128), ``sigma_depth`` (1): edge-stopping parameters
      (paper).
    - ``iterations`` (5): a-trous passes (paper).
    - ``min_temporal_history`` (4): shorter histories use the spatial variance estimate (paper).
    - ``variance_radius`` (3): the 7x7 bilateral window of that estimate (paper), weighted by the same
      depth and normal terms as the a-trous passes.
    - ``albedo_epsilon`` (0.01): floor of the albedo divisor (ours; the paper demodulates rasterised
      albedo, which has no zero-albedo samples of escaped paths).
    - ``reprojection_depth_tolerance`` (0.1), ``reprojection_normal_cos`` (0.9): the consistency tests
      of reprojected taps (ours: relative depth difference at most 10 %, normals within ~25 degrees; the
      paper names the tests but not their thresholds).

    Inputs: per-sample radiance (the filter sees its mean and per-sample luminance moments), mean albedo,
    normal and depth (first non-specular vertex, so reflections keep their own edges); pixel-centre
    motion, valid mask, G-buffer depth and normal for reprojection. With S samples per pixel the second
    moment is the mean of the per-sample squared luminance, and the variance of the filtered input (the
    S-sample mean) is (m2 - m1^2) / S; for S = 1 this is the paper's estimate.
    """

    def __init__(self, alpha_color: float = 0.2, alpha_moments: float = 0.2, sigma_luminance: float = 4.0,
                 sigma_normal: float = 128.0, sigma_depth: float = 1.0, iterations: int = 5,
                 min_temporal_history: int = 4, variance_radius: int = 3, albedo_epsilon: float = 0.01,
                 reprojection_depth_tolerance: float = 0.1, reprojection_normal_cos: float = 0.9) -> None:
        super().__init__()
        for name, value in (("alpha_color", alpha_color), ("alpha_moments", alpha_moments)):
            if not 0 < float(value) <= 1:
                raise ValueError(f"svgf: {name} must be in (0, 1], got {value}")
        for name, value in (("sigma_luminance", sigma_luminance), ("sigma_normal", sigma_normal),
                            ("sigma_depth", sigma_depth), ("albedo_epsilon", albedo_epsilon),
                            ("reprojection_depth_tolerance", reprojection_depth_tolerance)):
            if not float(value) > 0:
                raise ValueError(f"svgf: {name} must be > 0, got {value}")
        if int(iterations) < 1 or int(variance_radius) < 1 or int(min_temporal_history) < 1:
            raise ValueError("svgf: iterations, variance_radius and min_temporal_history must be >= 1")
        self.alpha_color = float(alpha_color)
        self.alpha_moments = float(alpha_moments)
        self.sigma_luminance = float(sigma_luminance)
        self.sigma_normal = float(sigma_normal)
        self.sigma_depth = float(sigma_depth)
        self.iterations = int(iterations)
        self.min_temporal_history = int(min_temporal_history)
        self.variance_radius = int(variance_radius)
        self.albedo_epsilon = float(albedo_epsilon)
        self.reprojection_depth_tolerance = float(reprojection_depth_tolerance)
        self.reprojection_normal_cos = float(reprojection_normal_cos)
        self._history: History | None = None
        self._workspace: PairWorkspace | None = None
        self._gathered: torch.Tensor | None = None
        #: Implementation of the a-trous passes in the last ``denoise`` call: "native" or "torch".
        self.backend = "torch"

    def reset(self) -> None:
        self._history = None

    # ---------------------------------------------------------------------------------------------
    def _albedo(self, frame: Frame) -> torch.Tensor:
        """(3, H, W) albedo the illumination is demodulated by (floored at ``albedo_epsilon``)."""
        return sanitize(frame.mean("albedo")).clamp_min_(self.albedo_epsilon)

    def _edge_depth(self, frame: Frame, gbuffer_depth: torch.Tensor) -> torch.Tensor:
        """(1, H, W) depth of the edge-stopping weights: the mean of the frame's samples."""
        return sanitize(frame.mean("depth")).abs_()

    def _normals(self, frame: Frame, gbuffer_depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """((3, H, W) unit normal of the frame's samples, (3, H, W) unit G-buffer normal for reprojection)."""
        normal = normalize_vectors(sanitize(frame.mean("normal")))
        gbuffer_normal = normalize_vectors(sanitize(frame.pixel["gbuffer.normal"]))
        # Environment pixels (G-buffer miss: depth 0, no normal) get the unit normal +z, so the
        # reprojection tests keep exactly their environment taps: depth 0 is within the tolerance
        # (0 x relative) of depth 0 only, and the normals agree.
        gbuffer_normal[2:3].add_(torch.le(gbuffer_depth, 0.0).float())
        return normal, gbuffer_normal

    def denoise(self, frame: Frame) -> torch.Tensor:
        check_sizes(self.info.name, {**frame.samples, **frame.pixel})
        radiance = sanitize(frame.samples["radiance"])                       # (S, 3, H, W), a fresh copy
        spp = radiance.shape[0]
        albedo = self._albedo(frame)
        illumination_samples = radiance.div_(albedo)
        illumination = illumination_samples.mean(dim=0)
        sample_luminance = luminance(illumination_samples)                     # (S, 1, H, W)
        first_moment = sample_luminance.mean(dim=0)
        moments = torch.cat([first_moment, sample_luminance.square_().mean(dim=0)])
        gbuffer_depth = sanitize(frame.pixel["gbuffer.depth"])
        depth = self._edge_depth(frame, gbuffer_depth)
        normal, gbuffer_normal = self._normals(frame, gbuffer_depth)

        integrated, integrated_moments, length = self._accumulate(frame, illumination, moments, gbuffer_depth,
                                                                  gbuffer_normal)

        # Variance of the filtered signal: temporal where the history is long enough, spatial elsewhere.
        gradient = depth_gradient(depth)
        self.backend = native.backend()
        # The torch a-trous passes take over geometric terms of the spatial estimate; the native ones need none.
        geometry = None if self.backend == "native" else GeometryTerms(
            self.sigma_normal, self.sigma_depth, self._workspace_for(*depth.shape[-2:]), normal, depth, gradient)
        variance = moment_variance(integrated_moments, spp)
        if float(length.min()) < self.min_temporal_history:
            short = length < self.min_temporal_history
            spatial_moments = self._spatial_moments(integrated_moments, normal, depth, gradient, short,
                                                    geometry)
            variance = torch.where(short, moment_variance(spatial_moments, spp), variance)

        # Variance-guided a-trous iterations; the first one's output is the colour history.
        filtered, history_illumination = self._atrous(integrated, variance, normal, depth, gradient,
                                                      geometry)

        # The state buffer is reused from frame to frame (the reprojection above was its last reader).
        state = self._history.state if self._history is not None else None
        if state is None or state.shape[-2:] != depth.shape[-2:]:
            state = torch.empty(10, *depth.shape[-2:])
        torch.cat([history_illumination, integrated_moments, length, gbuffer_depth, gbuffer_normal], out=state)
        self._history = History(state=state, index=frame.index)
        return filtered * albedo

    # ---------------------------------------------------------------------------------------------
    def _atrous(self, illumination: torch.Tensor, variance: torch.Tensor, normal: torch.Tensor,
                depth: torch.Tensor, gradient: torch.Tensor, geometry: GeometryTerms | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``iterations`` variance-guided a-trous passes: (filtered (3, H, W), first pass's output).

        Each pass is :func:`denoisers.filters.atrous_step` with :meth:`_all_terms` and the scales of
        :meth:`_depth_scales`, i.e. the weight of the class docstring
        w = exp(S(p, q) - a_l(p) |l_p - l_q| - a_z(p, o) |z_p - z_q|), S = sigma_n log max(0, n_p . n_q)
        + log h, written out because it is the hot loop of the method: log-weights are base 2 (exp2 is
        several times faster than exp), the geometric part comes from :class:`GeometryTerms` (computed
        once per pixel offset for both taps, and handed over to the next pass that visits the offset
        again), and both taps of a pair are weighted, accumulated and variance-accumulated by single ops
        on the views of a :class:`denoisers.filters.PairWorkspace` kept across frames.
        geometry: this frame's terms when the caller has them (possibly with terms handed over by the
        spatial variance estimate), otherwise made here from normal (3, H, W), depth (1, H, W) and
        gradient (2, H, W).

        With the native kernels (:mod:`denoisers.native`, unless ``MCDN_NATIVE=0``) the same passes run
        as one fused C++ loop per pass instead, and ``geometry`` is not used.
        """
        kernels = native.load() if illumination.device.type == "cpu" else None   # C++ on host memory
        if kernels is not None and illumination.dtype == torch.float32:
            filtered, history = kernels.svgf_atrous(
                illumination.contiguous(), variance.contiguous(), normal.contiguous(), depth.contiguous(),
                gradient.contiguous(), self.iterations, self.sigma_luminance, self.sigma_normal, self.sigma_depth,
                cosine_floor(self.sigma_normal), LUMINANCE_EPSILON, DEPTH_EPSILON_RELATIVE, MIN_LOG2_WEIGHT)
            return filtered, history
        _, height, width = illumination.shape
        workspace = self._workspace_for(height, width)
        if geometry is None:
            geometry = GeometryTerms(self.sigma_normal, self.sigma_depth, workspace, normal, depth, gradient)
        radius = (len(B3_SPLINE) - 1) // 2
        centre_h = B3_SPLINE[radius] ** 2
        ln2 = math.log(2.0)
        values, variances = workspace["values"], workspace["variance"]   # (2, 4, H, W), (2, 1, H, W)
        accumulated, variance_accumulated = workspace["accumulated"], workspace["variance_accumulated"]
        values[:, :3] = illumination
        variances[:] = variance
        history = illumination
        for i in range(self.iterations):
            last = i + 1 == self.iterations
            current_variance = variances[0]
            deviation = gaussian_blur_3x3(current_variance).clamp_min_(0).sqrt_()
            torch.reciprocal(deviation.mul_(self.sigma_luminance * ln2).add_(LUMINANCE_EPSILON * ln2),
                             out=workspace["luminance_scale"])     # a_l log2 e
            red, green, blue = values[0, 0:1], values[0, 1:2], values[0, 2:3]
            lum = torch.mul(red, REC709_LUMINANCE[0], out=workspace["luminance"])
            lum.add_(green, alpha=REC709_LUMINANCE[1]).add_(blue, alpha=REC709_LUMINANCE[2])
            torch.mul(values[0], centre_h, out=accumulated[0])
            accumulated[1].zero_()
            if not last:
                torch.mul(current_variance, centre_h ** 2, out=variance_accumulated[0])
                variance_accumulated[1].zero_()
            for region, ti, tj in workspace.regions(radius, 2 ** i):
                log2_h = math.log2(B3_SPLINE[radius + ti] * B3_SPLINE[radius + tj])
                geometric = geometry.log2_weights(region, log2_h)
                luminance_distance = torch.sub(workspace.first("luminance", region),
                                               workspace.second("luminance", region)).abs_()
                if not last and revisited_next_step(ti, tj):
                    geometry.keep(region, log2_h)
                    weight = torch.addcmul(geometric, workspace.pair("luminance_scale", region),
                                           luminance_distance, value=-1.0)
                else:
                    weight = geometric.addcmul_(workspace.pair("luminance_scale", region), luminance_distance,
                                                value=-1.0)
                weight.clamp_min_(MIN_LOG2_WEIGHT).exp2_()                      # (2, 1, h, w): taps +o, -o
                workspace.straight("accumulated", region).addcmul_(workspace.crossed("values", region), weight)
                if not last:    # the variance after the last pass is not used
                    workspace.straight("variance_accumulated", region).addcmul_(
                        workspace.crossed("variance", region), weight.square_())
            total = accumulated[0].add_(accumulated[1])
            weight_sum = total[3:]
            if not last:    # the next pass's input, straight into both copies
                torch.div(total[:3], weight_sum, out=values[0, :3])
                values[1, :3] = values[0, :3]
                torch.add(variance_accumulated[0], variance_accumulated[1], out=variances[0])
                variances[0].div_(weight_sum.square_())
                variances[1] = variances[0]
                if i == 0:
                    history = values[0, :3].clone()
            else:
                filtered = total[:3] / weight_sum
                if i == 0:
                    history = filtered
        return filtered, history

    def _workspace_for(self, height: int, width: int) -> PairWorkspace:
        """The a-trous buffers for this image size (rebuilt when the size changes)."""
        workspace = self._workspace
        if workspace is None or (workspace.height, workspace.width) != (height, width):
            workspace = PairWorkspace(height, width,
                                      images={"normal0": 1, "normal1": 1, "normal2": 1, "depth": 1, "depth_scale": 1,
                                              "luminance": 1, "luminance_scale": 1},
                                      doubled={"values": 4, "variance": 1, "accumulated": 4,
                                               "variance_accumulated": 1, "moments": 3, "moments_accumulated": 3})
            # The ones channels accumulate the weight sums.
            workspace["values"][:, 3] = 1.0
            workspace["moments"][:, 2] = 1.0
            self._workspace = workspace
        return workspace

    def _usable_history(self, frame: Frame, depth: torch.Tensor) -> History | None:
        """The history if it continues into ``frame`` (no cut, no gap, same size), else None."""
        history = self._history
        if (history is None or frame.camera_cut or frame.index != history.index + 1
                or history.depth.shape != depth.shape):
            return None
        return history

    def _accumulate(self, frame: Frame, illumination: torch.Tensor, moments: torch.Tensor, depth: torch.Tensor,
                    normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Temporal accumulation of this frame's illumination (3, H, W) and luminance moments (2, H, W), given
        its G-buffer depth (1, H, W) and unit normal (3, H, W): (integrated illumination, integrated moments,
        history length (1, H, W) in frames), all (C, H, W).

        Reprojects the history (:meth:`_reproject`) and blends with weight max(alpha, 1 / length); without
        a usable history the frame starts one. With the native kernels (:mod:`denoisers.native`) the same
        runs as one C++ pass over the pixels.
        """
        history = self._usable_history(frame, depth)
        if history is None:
            return illumination, moments, torch.ones_like(depth)
        kernels = native.load() if illumination.device.type == "cpu" else None
        if kernels is not None:
            integrated, integrated_moments, length = kernels.svgf_temporal(
                history.state, frame.pixel["motion"].float().contiguous(), frame.pixel["valid"].float().contiguous(),
                depth.contiguous(), normal.contiguous(), illumination.contiguous(), moments.contiguous(),
                self.reprojection_depth_tolerance, self.reprojection_normal_cos, self.alpha_color,
                self.alpha_moments, MIN_REPROJECTION_WEIGHT, MAX_HISTORY)
            return integrated, integrated_moments, length
        previous, success = self._reproject(frame, depth, normal)
        prev_illumination, prev_moments, prev_length = previous.split([3, 2, 1])
        # success ? min(prev + 1, MAX) : 1, as arithmetic (torch.where is slow on the CPU).
        length = (prev_length + 1).clamp_max_(MAX_HISTORY).sub_(1).mul_(success).add_(1)
        alpha_c = torch.clamp(1.0 / length, min=self.alpha_color)
        alpha_m = torch.clamp(1.0 / length, min=self.alpha_moments)
        return torch.lerp(prev_illumination, illumination, alpha_c), torch.lerp(prev_moments, moments, alpha_m), length

    def _reproject(self, frame: Frame, depth: torch.Tensor, normal: torch.Tensor
                   ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Previous [illumination, moments, length] (6, H, W) at this frame's pixels and the (1, H, W)
        success mask (float 1 / 0), or (None, None) when there is no usable history."""
        history = self._usable_history(frame, depth)
        if history is None:
            return None, None
        motion = sanitize(frame.pixel["motion"])
        valid = sanitize(frame.pixel["valid"])
        valid = torch.gt(valid, 0.5, out=valid)     # masks are float 0 / 1: bool ops are slow on the CPU
        indices, weights, inside = bilinear_footprint(motion)                   # (4, H, W) each
        weights = weights.mul_(inside).mul_(valid)                              # taps outside or invalid: 0
        _, height, width = depth.shape
        state = history.state.view(10, -1)
        if self._gathered is None or self._gathered.shape != state.shape:
            self._gathered = torch.empty_like(state)
        at_tap = self._gathered.view(10, height, width)
        depth_tolerance = depth * self.reprojection_depth_tolerance
        previous = torch.zeros(6, height, width)
        weight_sum = torch.zeros(1, height, width)
        # One tap at a time: all history channels gathered at that tap into a buffer kept across frames
        # (fresh multi-megabyte temporaries cost page faults every frame), then its consistency tests.
        for tap in range(indices.shape[0]):
            torch.index_select(state, 1, indices[tap].view(-1), out=self._gathered)
            depth_difference = (at_tap[6:7] - depth).abs_()
            cosine = at_tap[7:8] * normal[0:1]
            cosine.addcmul_(at_tap[8:9], normal[1:2]).addcmul_(at_tap[9:10], normal[2:3])
            tap_weight = torch.le(depth_difference, depth_tolerance, out=depth_difference)
            tap_weight.mul_(torch.ge(cosine, self.reprojection_normal_cos, out=cosine)).mul_(weights[tap:tap + 1])
            previous.addcmul_(at_tap[:6], tap_weight)
            weight_sum += tap_weight
        success = torch.gt(weight_sum, MIN_REPROJECTION_WEIGHT, out=torch.empty_like(weight_sum))
        previous /= weight_sum.clamp_min_(MIN_REPROJECTION_WEIGHT)
        return previous, success

    def _spatial_moments(self, moments: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                         gradient: torch.Tensor, where: torch.Tensor, geometry: GeometryTerms | None = None
                         ) -> torch.Tensor:
        """(2, H, W) moments averaged over a (2r + 1)^2 window with the depth and normal weights of the
        a-trous passes (no luminance term); only pixels in ``where`` (1, H, W) bool are guaranteed.

        Dense (shifted views over the image) when many pixels need it, otherwise gathered at just those
        pixels -- in a moving scene the few disoccluded pixels would not pay for a full-image pass.
        The dense estimate is :func:`denoisers.filters.atrous_step` with a box window, :meth:`_geometry_terms`
        and :meth:`_depth_scales`, written out like :meth:`_atrous`; given this frame's ``geometry``,
        it hands the terms of the offsets within the 5x5 kernel over to the first a-trous pass.
        """
        if float(where.float().mean()) > SPARSE_VARIANCE_FRACTION:
            _, height, width = moments.shape
            workspace = self._workspace_for(height, width)
            if geometry is None:
                geometry = GeometryTerms(self.sigma_normal, self.sigma_depth, workspace, normal, depth, gradient)
            values, accumulated = workspace["moments"], workspace["moments_accumulated"]   # (2, 3, H, W)
            values[:, :2] = moments
            accumulated[0] = values[0]    # the centre tap, weight 1
            accumulated[1].zero_()
            atrous_radius = (len(B3_SPLINE) - 1) // 2
            for region, i, j in workspace.regions(self.variance_radius, 1):
                geometric = geometry.log2_weights(region, 0.0)      # box window: log2 h = 0
                if abs(i) <= atrous_radius and abs(j) <= atrous_radius:
                    geometry.keep(region, 0.0)
                    weight = torch.clamp_min(geometric, MIN_LOG2_WEIGHT).exp2_()
                else:
                    weight = geometric.clamp_min_(MIN_LOG2_WEIGHT).exp2_()
                workspace.straight("moments_accumulated", region).addcmul_(workspace.crossed("moments", region),
                                                                           weight)
            total = accumulated[0].add_(accumulated[1])
            return total[:2] / total[2:]
        _, height, width = moments.shape
        centres = where.reshape(-1).nonzero().squeeze(1)                         # (K,)
        cy, cx = centres // width, centres % width
        span = torch.arange(-self.variance_radius, self.variance_radius + 1)
        oy, ox = torch.meshgrid(span, span, indexing="ij")
        oy, ox = oy.reshape(-1, 1), ox.reshape(-1, 1)                             # (T, 1) tap offsets
        qy, qx = cy + oy, cx + ox                                                 # (T, K)
        inside = (qy >= 0) & (qy < height) & (qx >= 0) & (qx < width)
        neighbours = (qy.clamp(0, height - 1) * width + qx.clamp(0, width - 1)).reshape(-1)
        stacked = torch.cat([moments, normal, depth]).reshape(6, -1)
        at_q = torch.index_select(stacked, 1, neighbours).view(6, *qy.shape)     # (6, T, K)
        at_p = torch.index_select(stacked, 1, centres)[:, None]                  # (6, 1, K)
        slope = torch.index_select(gradient.reshape(2, -1), 1, centres)           # (2, K)
        cosine = (at_p[2:5] * at_q[2:5]).sum(dim=0).clamp_min_(NORMAL_COSINE_FLOOR)
        depth_scale = 1.0 / ((slope[0] * ox + slope[1] * oy).abs_().mul_(self.sigma_depth)
                             .add_(at_p[5] * DEPTH_EPSILON_RELATIVE + 1e-6))
        exponent = cosine.log_().mul_(self.sigma_normal).sub_((at_p[5] - at_q[5]).abs_() * depth_scale)
        weights = exponent.clamp_min_(MIN_LOG_WEIGHT).exp_() * inside
        weights[(oy == 0).squeeze(1) & (ox == 0).squeeze(1)] = 1.0               # w(p, p) = 1
        averaged = (at_q[0:2] * weights).sum(dim=1) / weights.sum(dim=0)          # (2, K)
        filtered = moments.clone()
        filtered.reshape(2, -1)[:, centres] = averaged
        return filtered

    # The per-pair terms in the form of :func:`denoisers.filters.atrous_step`'s callbacks: the reference
    # formulation that :meth:`_atrous` and the dense :meth:`_spatial_moments` write out (the tests run
    # both and compare).
    def _geometry_terms(self, at_p: dict[str, torch.Tensor], at_q: dict[str, torch.Tensor]):
        """Symmetric terms: sigma_n log max(0, n_p . n_q) and [|z_p - z_q|]."""
        cosine = (at_p["n"] * at_q["n"]).sum(dim=0, keepdim=True).clamp_min_(NORMAL_COSINE_FLOOR)
        return cosine.log_().mul_(self.sigma_normal), [(at_p["z"] - at_q["z"]).abs_()]

    def _all_terms(self, at_p: dict[str, torch.Tensor], at_q: dict[str, torch.Tensor]):
        """Symmetric terms of the a-trous weight: normal log-weight and [|l_p - l_q|, |z_p - z_q|]."""
        normal_term, (depth_distance,) = self._geometry_terms(at_p, at_q)
        return normal_term, [(at_p["l"] - at_q["l"]).abs_(), depth_distance]

    def _depth_scales(self, depth: torch.Tensor, gradient: torch.Tensor):
        """(dy, dx) -> [1 / (sigma_z |grad z . (dx, dy)| + eps)] per centre pixel, (1, H, W).

        |grad z . o| is cached per direction o / gcd(o), shared by all iterations.
        """
        floor = depth * DEPTH_EPSILON_RELATIVE + 1e-6
        projections: dict[tuple[int, int], torch.Tensor] = {}

        def scales(dy: int, dx: int) -> list[torch.Tensor]:
            length = math.gcd(dy, dx)
            direction = (dy // length, dx // length)
            if direction not in projections:
                projections[direction] = (gradient[0:1] * direction[1] + gradient[1:2] * direction[0]).abs_()
            return [(projections[direction] * (self.sigma_depth * length)).add_(floor).reciprocal_()]

        return scales
