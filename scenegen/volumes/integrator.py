"""A volumetric path tracer that also returns per-sample features for volume denoising.

Registered as the Mitsuba integrator ``"mcdn_volpath_features"``. The radiance estimator is the one of
Mitsuba's built-in ``volpath`` (its sample mean converges to ``volpath``'s image on the same scene;
``tests/test_volume_integrator.py`` checks this with independent passes):

* free-flight sampling by delta tracking against the medium's majorant (``medium.sample_interaction``
  with one RGB channel chosen per path, throughput x transmittance / free-flight pdf of that channel);
  a tentative collision is real with probability P = mean_RGB(sigma_t / majorant) (weight sigma_s / P,
  then a phase-function scatter) and null otherwise (weight sigma_n / (1 - P), the ray goes on);
  homogeneous media have P = 1. Any phase function works through ``phase.sample`` / ``phase.eval_pdf``;
* next-event estimation at medium events and at surfaces with a smooth BSDF: one emitter sample, whose
  transmittance is estimated by ratio tracking along the shadow ray (heterogeneous media: product of
  sigma_n / majorant at tentative collisions; homogeneous media: analytic exp(-sigma_t d)), passing
  through null surfaces with ``bsdf.eval_null_transmission`` (0 at opaque ones) and following medium
  transitions (``si.target_medium``);
* emitters hit by phase/BSDF sampling are weighted against emitter sampling with the power heuristic
  (no MIS on camera rays and after Dirac chains); null surfaces keep the last real vertex for MIS;
* ``max_depth`` (default -1 = unlimited) and ``rr_depth`` (default 5) count real scattering events
  (medium scatters and non-null BSDF samples) exactly as ``volpath``: 1 = emitters seen directly
  (through media), 2 = direct illumination / single scattering; Russian roulette once depth > rr_depth with survival
  probability min(max(throughput) x eta^2, 0.95). ``hide_emitters`` as in ``volpath`` (emission on
  the camera segment is not counted). A camera inside a medium starts in ``sensor.get_medium()``
  (``mi.render`` passes it; direct ``sample()`` calls must pass it as ``medium``).

Per sample it returns 10 AOV channels (``aov_names()``: ``position.R/G/B``, ``depth.Y``, ``sigma_t.Y``,
``albedo.R/G/B``, ``medium.Y``, ``transmittance.Y``, the naming of ``scenegen.integrator``); the first
five are 0 when the camera ray escapes without a real collision:

* at the first *real* collision of the camera ray (the first medium scatter event chosen by delta
  tracking, or the first surface whose BSDF has a non-null lobe; null surfaces are passed through):
  ``position`` (3, world space, scene units), ``depth`` (1, distance along the camera ray from its
  origin, scene units -- for Mitsuba's perspective camera the origin lies on the near-clip plane, as
  for the surface integrator's depth), ``sigma_t`` (1, RGB mean of the extinction at the
  event, 1/scene unit; 0 on a surface), ``albedo`` (3, RGB in [0, 1]: single-scattering albedo
  sigma_s / sigma_t at a medium event; on a surface Mitsuba's ``eval_diffuse_reflectance`` clamped to
  [0, 1] -- the base colour of diffuse-type BSDFs, Mitsuba's default for others), ``medium`` (1:
  1 for a medium event, 0 for a surface or an escape);
* ``transmittance`` (1, in [0, 1]): the camera ray's transmittance from its origin to its first real
  surface (to infinity if it escapes), estimated by ratio tracking (RGB mean; exact in homogeneous
  media) with its own random numbers, through null surfaces. Its expectation equals 1 - E[medium flag]
  for grey extinction, with a lower per-sample variance.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from scenegen.integrator import _mis_weight, aov_channel_names

VOLUME_AOVS: tuple[tuple[str, int], ...] = (
    ("position", 3),
    ("depth", 1),
    ("sigma_t", 1),
    ("albedo", 3),
    ("medium", 1),
    ("transmittance", 1),
)
_UNLIMITED = 2**32 - 1


def _real_bsdf(bsdf: mi.BSDFPtr) -> mi.Bool:
    """True where the BSDF has any lobe besides the null (pass-through) one (side flags ignored)."""
    return (bsdf.flags() & (int(mi.BSDFFlags.All) & ~int(mi.BSDFFlags.Null))) != 0


def _channel_value(spec: mi.Spectrum, channel: mi.UInt32) -> mi.Float:
    """Component ``channel`` (0..2) of an RGB spectrum."""
    return dr.select(channel == 0, spec[0], dr.select(channel == 1, spec[1], spec[2]))


class VolumeFeatureIntegrator(mi.SamplingIntegrator):
    """Volumetric path tracer returning radiance plus per-sample volume AOVs (see module docstring)."""

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        max_depth = int(props.get("max_depth", -1))
        self.rr_depth = int(props.get("rr_depth", 5))
        if max_depth < -1:
            raise ValueError(f"mcdn_volpath_features: max_depth must be >= -1, got {max_depth}")
        if self.rr_depth < 1:
            raise ValueError(f"mcdn_volpath_features: rr_depth must be >= 1, got {self.rr_depth}")
        self.max_depth = _UNLIMITED if max_depth == -1 else max_depth

    def aov_names(self) -> list[str]:
        return aov_channel_names(VOLUME_AOVS)

    def to_string(self) -> str:
        return (f"VolumeFeatureIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"hide_emitters={self.hide_emitters}]")

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        start = dr.zeros(mi.MediumPtr) if medium is None else mi.MediumPtr(medium)
        return self._sample(scene, sampler, mi.Ray3f(ray), start, mi.Bool(active))

    @dr.syntax
    def _ratio_track(self, scene: mi.Scene, sampler: mi.Sampler, ray_in: mi.Ray3f, medium_in: mi.MediumPtr,
                     channel: mi.UInt32, active_in: mi.Bool, stop_at_surfaces: bool) -> mi.Spectrum:
        """Transmittance from ``ray_in.o`` over ``ray_in.maxt`` by ratio tracking, starting in
        ``medium_in``. Null surfaces multiply by their null transmission; a real surface gives 0 or,
        with ``stop_at_surfaces``, ends the estimate there (the camera transmittance)."""
        ray = mi.Ray3f(ray_in)
        medium = mi.MediumPtr(medium_in)
        active = mi.Bool(active_in)
        remaining = mi.Float(ray_in.maxt)
        tr = mi.Spectrum(1.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        stop = mi.Bool(stop_at_surfaces)
        while active:
            ray.maxt = remaining
            intersect = active & needs_intersection
            si[intersect] = scene.ray_intersect(ray, intersect)
            needs_intersection &= ~intersect
            in_medium = active & (medium != None)  # noqa: E711 -- drjit pointer comparison
            mei = medium.sample_interaction(ray, sampler.next_1d(in_medium), channel, in_medium)
            # Homogeneous media: analytic transmittance up to the surface or the end of the segment.
            homogeneous = in_medium & medium.is_homogeneous()
            mei.t[homogeneous] = dr.minimum(remaining, si.t)
            tr_h, _ = medium.transmittance_eval_pdf(mei, si, homogeneous)
            tr[homogeneous] *= tr_h
            mei.t[homogeneous | (si.t < mei.t)] = dr.inf
            collide = in_medium & mei.is_valid()
            tr[collide] *= mei.sigma_n / mei.combined_extinction
            ray.o[collide] = mei.p
            si.t[collide] = si.t - mei.t
            remaining[collide] = remaining - mei.t
            # Surfaces (after leaving the medium segment, or outside media).
            surface = active & ~collide & si.is_valid()
            bsdf = si.bsdf(ray)
            end_here = surface & stop & _real_bsdf(bsdf)
            surface &= ~end_here
            tr[surface] *= bsdf.eval_null_transmission(si, surface)
            medium[surface & si.is_medium_transition()] = si.target_medium(ray.d)
            remaining[surface] = remaining - si.t
            ray[surface] = si.spawn_ray(ray.d)
            needs_intersection |= surface
            active &= (collide | surface) & dr.any(tr != 0.0) & (remaining > 0.0)
        return tr

    @dr.syntax
    def _sample(self, scene: mi.Scene, sampler: mi.Sampler, ray_in: mi.Ray3f, medium_in: mi.MediumPtr,
                active_in: mi.Bool):
        hide = bool(self.hide_emitters)
        ray = mi.Ray3f(ray_in)
        medium = mi.MediumPtr(medium_in)
        active = mi.Bool(active_in)
        channel = mi.UInt32(dr.minimum(3.0 * sampler.next_1d(active), 2.0))
        cam_tr = self._ratio_track(scene, sampler, ray_in, medium_in, channel, active, True)

        depth = mi.UInt32(0)
        L = mi.Spectrum(0.0)
        throughput = mi.Spectrum(1.0)
        eta = mi.Float(1.0)
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        last_event = dr.zeros(mi.Interaction3f)
        last_pdf = mi.Float(1.0)
        specular_chain = mi.Bool(not hide)
        valid = mi.Bool(not hide and scene.environment() is not None)
        # Features at the first real collision.
        found = mi.Bool(False)
        f_position = mi.Point3f(0.0)
        f_sigma_t = mi.Float(0.0)
        f_albedo = mi.Color3f(0.0)
        f_medium = mi.Float(0.0)

        while active:
            # ---- Russian roulette and depth limit (as volpath, at the top of the loop) ----
            active &= dr.any(throughput != 0.0)
            q = dr.minimum(dr.max(throughput) * dr.square(eta), 0.95)
            perform_rr = depth > self.rr_depth
            active &= (sampler.next_1d(active) < q) | ~perform_rr
            throughput[perform_rr] = throughput * dr.rcp(q)
            active &= depth < self.max_depth

            # ---- delta tracking in the current medium ----
            in_medium = active & (medium != None)  # noqa: E711
            on_surface = active & ~in_medium
            mei = medium.sample_interaction(ray, sampler.next_1d(in_medium), channel, in_medium)
            # Homogeneous media only have real collisions: no surface beyond mei.t matters.
            ray.maxt[in_medium & medium.is_homogeneous() & mei.is_valid()] = mei.t
            intersect = needs_intersection & in_medium
            si[intersect] = scene.ray_intersect(ray, intersect)
            needs_intersection &= ~in_medium
            mei.t[in_medium & (si.t < mei.t)] = dr.inf
            tr, free_flight_pdf = medium.transmittance_eval_pdf(mei, si, in_medium)
            pdf_c = _channel_value(free_flight_pdf, channel)
            throughput[in_medium] = throughput * dr.select(pdf_c > 0.0, tr / pdf_c, 0.0)
            escaped = in_medium & ~mei.is_valid()
            collide = in_medium & mei.is_valid()
            p_real = dr.mean(mei.sigma_t / mei.combined_extinction)
            real = collide & (sampler.next_1d(collide) < p_real)
            null = collide & ~real
            throughput[null] = throughput * mei.sigma_n / (1.0 - p_real)
            ray.o[null] = mei.p
            si.t[null] = si.t - mei.t

            latch = real & ~found
            f_position[latch] = mei.p
            f_sigma_t[latch] = dr.mean(mi.Color3f(mei.sigma_t))
            f_albedo[latch] = dr.select(mei.sigma_t > 0.0, mei.sigma_s / mei.sigma_t, 0.0)
            f_medium[latch] = 1.0
            found |= latch

            depth[real] += 1
            last_event[real] = mei
            active &= depth < self.max_depth
            real &= active
            throughput[real] = throughput * mei.sigma_s / p_real
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            sample_emitters = mei.medium.use_emitter_sampling()
            specular_chain &= ~real
            specular_chain |= real & ~sample_emitters
            valid |= real

            # ---- surfaces: emission found by phase/BSDF sampling, or seen through media ----
            on_surface |= escaped
            intersect = on_surface & needs_intersection
            si[intersect] = scene.ray_intersect(ray, intersect)
            emitter = si.emitter(scene)
            hit_emitter = on_surface & (emitter != None) & ~(mi.Bool(hide) & (depth == 0))  # noqa: E711
            count_direct = (depth == 0) | specular_chain
            ds_hit = mi.DirectionSample3f(scene, si, last_event)
            em_pdf = scene.pdf_emitter_direction(last_event, ds_hit, hit_emitter & ~count_direct)
            mis_hit = dr.select(count_direct, 1.0, _mis_weight(last_pdf, em_pdf))
            L[hit_emitter] = L + throughput * mis_hit * emitter.eval(si, hit_emitter)
            on_surface &= si.is_valid()
            bsdf = si.bsdf(ray)

            latch = on_surface & ~found & _real_bsdf(bsdf)
            f_position[latch] = si.p
            f_albedo[latch] = dr.clip(bsdf.eval_diffuse_reflectance(si, latch), 0.0, 1.0)
            found |= latch

            # ---- next-event estimation (medium events and smooth surfaces), ratio-tracked ----
            nee_medium = real & sample_emitters
            nee_surface = on_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < self.max_depth)
            nee = nee_medium | nee_surface
            ref = dr.zeros(mi.Interaction3f)
            ref[nee_medium] = mi.Interaction3f(mei)
            ref[nee_surface] = mi.Interaction3f(si)
            ds, em_weight = scene.sample_emitter_direction(ref, sampler.next_2d(nee), False, nee)
            nee &= ds.pdf != 0.0
            shadow_medium = mi.MediumPtr(medium)
            shadow_medium[nee_surface & si.is_medium_transition()] = si.target_medium(ds.d)
            shadow_tr = self._ratio_track(scene, sampler, ref.spawn_ray_to(ds.p), shadow_medium, channel,
                                          nee, False)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(mi.BSDFContext(), si, si.to_local(ds.d), nee_surface)
            phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, nee_medium)
            f_val = dr.select(nee_surface, bsdf_val, phase_val)
            dir_pdf = dr.select(ds.delta, 0.0, dr.select(nee_surface, bsdf_pdf, phase_pdf))
            L[nee] = L + throughput * f_val * _mis_weight(ds.pdf, dir_pdf) * em_weight * shadow_tr

            # ---- phase-function sampling ----
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sampler.next_1d(real),
                                                       sampler.next_2d(real), real)
            real &= phase_pdf > 0.0
            throughput[real] = throughput * phase_weight
            ray[real] = mei.spawn_ray(wo)
            needs_intersection |= real
            last_pdf[real] = phase_pdf

            # ---- BSDF sampling (null surfaces pass the ray through without a scattering event) ----
            bs, bsdf_weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(on_surface),
                                          sampler.next_2d(on_surface), on_surface)
            on_surface &= bs.pdf > 0.0
            throughput[on_surface] = throughput * bsdf_weight
            eta[on_surface] = eta * bs.eta
            ray[on_surface] = si.spawn_ray(si.to_world(bs.wo))
            needs_intersection |= on_surface
            non_null = on_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[non_null] += 1
            last_event[non_null] = mi.Interaction3f(si)
            last_pdf[non_null] = bs.pdf
            valid |= non_null
            specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(on_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            medium[on_surface & si.is_medium_transition()] = si.target_medium(ray.d)
            active &= on_surface | collide

        f_depth = dr.select(found, dr.norm(f_position - ray_in.o), 0.0)
        # Ratio tracking's factors 1 - sigma_t / majorant can round to -6e-8 where the grid meets its majorant.
        t_cam = dr.clip(dr.mean(mi.Color3f(cam_tr)), 0.0, 1.0)
        aovs = [f_position.x, f_position.y, f_position.z, f_depth, f_sigma_t,
                f_albedo.x, f_albedo.y, f_albedo.z, f_medium, t_cam]
        return L, valid, aovs


mi.register_integrator("mcdn_volpath_features", lambda props: VolumeFeatureIntegrator(props))
