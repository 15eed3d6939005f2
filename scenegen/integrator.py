"""A path tracer that also returns the per-sample features denoisers need.

Registered as the Mitsuba integrator ``"mcdn_features"``. Light transport is the same estimator
as Mitsuba's built-in ``path`` integrator (BSDF sampling and emitter sampling combined with the
power heuristic, Russian roulette after ``rr_depth``, ``max_depth`` counted the same way), so the
mean of its samples converges to ``path``'s image; ``tests/test_render.py`` checks this.

Per sample it returns, as AOVs (Isik et al. 2021, Sec. 3.1):

* ``diffuse`` (3): the part of the radiance that leaves the first non-specular vertex through a
  diffuse lobe (emitter sampling there is split exactly by evaluating the BSDF restricted to its
  diffuse lobes; the BSDF-sampled continuation goes to the lobe that was sampled). Everything
  else -- glossy reflection, emission seen directly or through a specular chain -- is
  ``specular = radiance - diffuse``.
* ``albedo`` (3), ``normal`` (3, world-space shading normal), ``roughness`` (1),
  ``position`` (3, world space) at the first non-specular vertex; 0 where the path escapes;
  ``depth`` (1): path length from the camera to that vertex (through mirrors and glass), metres.
* ``flags`` (4): emissive (that vertex is on an emitter, or the path escaped to an environment
  emitter), metallic (conductor there), transmissive (a refraction on the way there or a
  transmissive material there), specular bounce (the first camera vertex is specular).

The albedo follows the convention OIDN documents for its albedo input: view independent, in
[0, 1] (clamped). Diffuse-type BSDFs (diffuse, (rough)plastic, principled -- whose base colour is
also the specular colour of its metallic part) give their base colour incl. textures, Mitsuba's
``eval_diffuse_reflectance``; conductors their specular reflectance colour, ``specular_reflectance``
x the Fresnel reflectance at normal incidence ((eta-1)^2+k^2)/((eta+1)^2+k^2); dielectrics their
``specular_transmittance`` tint (1 by default). Conductor and dielectric colours are computed on
the host from the BSDF's parameters and stored per face (``face_albedo``). Where that attribute
is missing (analytic shapes of XML scenes, BSDFs wrapped in ``twosided``, textured conductor
parameters) a BSDF with a diffuse lobe gives its ``eval_diffuse_reflectance``, and any other BSDF
(and a ``blendbsdf`` mesh, whose diffuse reflectance is Mitsuba's view-dependent default) its
directional albedo at normal incidence, int f(n, wo) |cos wo| dwo, by deterministic quadrature
(``NORMAL_ALBEDO_POINTS`` BSDF samples at fixed low-discrepancy points: view independent, noise
free, and no dimensions of the path's sampler are used). That equals the colour above for a
smooth conductor; a dielectric gets R + (1 - R) x tint (R = 0.04 at eta 1.5); a rough conductor
loses its microfacet masking-shadowing (GGX alpha 0.3: < 0.1 %, alpha 0.6: 14 %), and the
quadrature is within a few percent at high roughness. A path whose specular chain ends early
(``max_depth``) takes the albedo of its last vertex.

A vertex counts as specular when its BSDF is purely Dirac (smooth mirror, glass) or is a
non-diffuse material with linear roughness below ``specular_roughness`` (0.1, as Isik et al.).
Material facts that Mitsuba's BSDF interface does not expose are read from per-face mesh
attributes written by ``scenegen.mitsuba_scene.attach_face_attributes``: ``face_material`` =
(roughness, metallic, transmissive), ``face_ident`` = (shape index, specular-like, albedo
source: 0 none / 1 ``face_albedo`` / 2 quadrature) and ``face_albedo`` (RGB).

With ``mode="gbuffer"`` the integrator returns only the primary hit (position, shading normal,
depth, shape index; -1 on a miss; and the hit's own albedo and roughness, as a rasterised G-buffer
holds them) and no light transport, for motion vectors and per-pixel features.

``hide_emitters`` (read by ``mi.SamplingIntegrator``) has the meaning of Mitsuba's ``path``: camera
rays pass through area emitters to the first surface behind them, and a camera ray that escapes
sees no environment emitter (black, not emissive); emitters still light the scene. The G-buffer
mode follows its own flag or that of the scene's integrator, so it sees the same first surface.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

SAMPLE_AOVS: tuple[tuple[str, int], ...] = (
    ("diffuse", 3),
    ("albedo", 3),
    ("normal", 3),
    ("depth", 1),
    ("roughness", 1),
    ("flags", 4),
    ("position", 3),
)
GBUFFER_AOVS: tuple[tuple[str, int], ...] = (
    ("position", 3),
    ("normal", 3),
    ("depth", 1),
    ("object", 1),
    ("albedo", 3),
    ("roughness", 1),
)
MATERIAL_ATTRIBUTE = "face_material"
IDENT_ATTRIBUTE = "face_ident"
ALBEDO_ATTRIBUTE = "face_albedo"
ALBEDO_SOURCE_ATTRIBUTE = 1.0
"""face_ident.z value: the albedo is the ``face_albedo`` attribute (0: decided per sample)."""
ALBEDO_SOURCE_QUADRATURE = 2.0
"""face_ident.z value: the albedo is the directional albedo at normal incidence."""
NORMAL_ALBEDO_POINTS = 64
# Additive recurrence with the generalised golden ratio in 3D (Roberts' R3 sequence): points for
# (sample1, sample2) of bsdf.sample spread jointly, so lobe choice and direction do not alias.
_R3 = 1.2207440845749
_R3_STEPS = (1.0 / _R3, 1.0 / _R3**2, 1.0 / _R3**3)
_CHANNEL_SUFFIX = {1: ("Y",), 3: ("R", "G", "B"), 4: ("0", "1", "2", "3")}


def aov_channel_names(aovs: tuple[tuple[str, int], ...]) -> list[str]:
    """Flat AOV channel names in the order the integrator returns them."""
    return [f"{name}.{suffix}" for name, size in aovs for suffix in _CHANNEL_SUFFIX[size]]


def _mis_weight(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    """Power heuristic (beta = 2), the weight Mitsuba's ``path`` uses; 0 where it is not finite (a pdf
    that overflows at grazing angles gives inf / inf), as ``path`` does."""
    a2 = dr.square(pdf_a)
    weight = a2 / (a2 + dr.square(pdf_b))
    return dr.detach(dr.select((pdf_a > 0) & dr.isfinite(weight), weight, 0.0))


@dr.syntax
def normal_incidence_albedo(bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Color3f:
    """Directional albedo of ``bsdf`` at ``si`` for light arriving along the shading normal,
    int f(n, wo) |cos wo| dwo over both hemispheres, by quadrature over ``NORMAL_ALBEDO_POINTS``
    fixed low-discrepancy BSDF samples (importance transport: no 1/eta^2 radiance scaling on
    refraction). View independent and deterministic; uses no sampler."""
    si_n = mi.SurfaceInteraction3f(si)
    si_n.wi = mi.Vector3f(0.0, 0.0, 1.0)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    total = mi.Color3f(0.0)
    i = mi.UInt32(0)
    while active & (i < NORMAL_ALBEDO_POINTS):
        x = mi.Float(i) + 0.5
        u1 = x * _R3_STEPS[0] - dr.floor(x * _R3_STEPS[0])
        u2 = mi.Point2f(x * _R3_STEPS[1] - dr.floor(x * _R3_STEPS[1]),
                        x * _R3_STEPS[2] - dr.floor(x * _R3_STEPS[2]))
        bs, weight = bsdf.sample(ctx, si_n, u1, u2, active)
        total += dr.select(bs.pdf > 0.0, mi.Color3f(weight), 0.0)
        i += 1
    return total / NORMAL_ALBEDO_POINTS


def feature_albedo(bsdf: mi.BSDFPtr, si: mi.SurfaceInteraction3f, source: mi.Float,
                   active: mi.Bool) -> mi.Color3f:
    """Albedo (RGB in [0, 1]) at the hit ``si`` following the module docstring; ``source`` is
    face_ident.z (0 where the shape has no attributes). 0 on inactive lanes."""
    from_attribute = active & (dr.abs(source - ALBEDO_SOURCE_ATTRIBUTE) < 0.5)
    quadrature = active & ((dr.abs(source - ALBEDO_SOURCE_QUADRATURE) < 0.5)
                           | ((source < 0.5) & ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)))
    from_diffuse = active & ~from_attribute & ~quadrature
    albedo = dr.select(from_attribute, si.shape.eval_attribute_3(ALBEDO_ATTRIBUTE, si, from_attribute), 0.0)
    albedo = dr.select(from_diffuse, bsdf.eval_diffuse_reflectance(si, from_diffuse), albedo)
    albedo = dr.select(quadrature, normal_incidence_albedo(bsdf, si, quadrature), albedo)
    return mi.Color3f(dr.clip(albedo, 0.0, 1.0))


class FeatureIntegrator(mi.SamplingIntegrator):
    """Path tracer returning radiance plus per-sample feature AOVs (see module docstring)."""

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        self.max_depth = int(props.get("max_depth", 8))
        self.rr_depth = int(props.get("rr_depth", 5))
        self.mode = str(props.get("mode", "samples"))
        self.specular_roughness = float(props.get("specular_roughness", 0.1))
        if self.max_depth < 1:
            raise ValueError(f"mcdn_features: max_depth must be >= 1, got {self.max_depth}")
        if self.rr_depth < 1:
            raise ValueError(f"mcdn_features: rr_depth must be >= 1, got {self.rr_depth}")
        if self.mode not in ("samples", "gbuffer"):
            raise ValueError(f"mcdn_features: mode must be 'samples' or 'gbuffer', got {self.mode!r}")

    def aov_names(self) -> list[str]:
        return aov_channel_names(SAMPLE_AOVS if self.mode == "samples" else GBUFFER_AOVS)

    def to_string(self) -> str:
        return (f"FeatureIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, mode={self.mode}, "
                f"hide_emitters={self.hide_emitters}]")

    def _skip_hidden_emitters(self, scene: mi.Scene, ray: mi.Ray3f, si: mi.SurfaceInteraction3f,
                              camera: mi.Bool) -> tuple[mi.SurfaceInteraction3f, mi.Float]:
        """hide_emitters: lanes in ``camera`` whose hit is an area emitter continue to the first
        surface behind all area emitters on the ray. Returns that interaction (``t`` measured from
        the last hidden emitter) and the distance from the ray origin to that emitter (0 elsewhere)."""
        skip = camera & si.is_valid() & (si.shape.emitter() != None)  # noqa: E711 -- drjit pointers
        ray_skip = si.spawn_ray(ray.d)
        behind = self.skip_area_emitters(scene, ray_skip, True, skip)
        si_behind = behind.compute_surface_interaction(ray_skip, mi.RayFlags.All, skip)
        offset = dr.select(skip, si.t, 0.0)
        si[skip] = si_behind
        return si, offset

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        if self.mode == "gbuffer":
            return self._sample_gbuffer(scene, ray, active)
        return self._sample_path(scene, sampler, ray, active)

    def _sample_gbuffer(self, scene: mi.Scene, ray: mi.Ray3f, active: mi.Bool):
        si = scene.ray_intersect(mi.Ray3f(ray), active)
        offset = mi.Float(0.0)
        if self.hide_emitters or (scene.integrator() is not None and scene.integrator().hide_emitters):
            si, offset = self._skip_hidden_emitters(scene, mi.Ray3f(ray), si, active)
        hit = active & si.is_valid()
        ident = si.shape.eval_attribute_3(IDENT_ATTRIBUTE, si, hit)
        obj = dr.select(hit, ident.x, -1.0)
        p = dr.select(hit, si.p, 0.0)
        n = dr.select(hit, si.sh_frame.n, 0.0)
        depth = dr.select(hit, offset + si.t, 0.0)
        # The primary hit's own albedo and roughness (a rasterised G-buffer's, Chaitanya et al. 2017 §3.1-3.2):
        # no specular chain is followed, unlike the per-sample features.
        albedo = feature_albedo(si.bsdf(mi.RayDifferential3f(ray)), si, ident.z, hit)
        roughness = dr.select(hit, si.shape.eval_attribute_3(MATERIAL_ATTRIBUTE, si, hit).x, 0.0)
        aovs = [p.x, p.y, p.z, n.x, n.y, n.z, depth, obj, albedo.x, albedo.y, albedo.z, roughness]
        return mi.Spectrum(0.0), hit, aovs

    @dr.syntax
    def _sample_path(self, scene: mi.Scene, sampler: mi.Sampler, ray_in: mi.RayDifferential3f,
                     active_in: mi.Bool):
        ctx = mi.BSDFContext()
        ctx_diffuse = mi.BSDFContext()
        ctx_diffuse.type_mask = mi.BSDFFlags.Diffuse

        ray = mi.Ray3f(ray_in)
        active = mi.Bool(active_in)
        depth = mi.UInt32(0)
        L = mi.Spectrum(0.0)
        L_diffuse = mi.Spectrum(0.0)
        throughput = mi.Spectrum(1.0)
        eta = mi.Float(1.0)
        prev_si = dr.zeros(mi.Interaction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)

        # Feature state: features are latched at the first non-specular vertex.
        on_spec_chain = mi.Bool(True)      # every vertex so far was specular
        diffuse_path = mi.Bool(False)      # contributions after the feature vertex go to diffuse
        path_length = mi.Float(0.0)
        f_albedo = mi.Color3f(0.0)
        f_normal = mi.Normal3f(0.0)
        f_position = mi.Point3f(0.0)
        f_depth = mi.Float(0.0)
        f_rough = mi.Float(0.0)
        f_emissive = mi.Bool(False)
        f_metallic = mi.Bool(False)
        f_transmissive = mi.Bool(False)
        f_spec_bounce = mi.Bool(False)
        refracted = mi.Bool(False)
        hide_emitters = bool(self.hide_emitters)

        while active:
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0))
            offset = mi.Float(0.0)
            if dr.hint(hide_emitters, mode="scalar"):
                si, offset = self._skip_hidden_emitters(scene, ray, si, active & (depth == 0))
            hit = si.is_valid()
            path_length += dr.select(hit, offset + si.t, 0.0)

            # ---- emission found by the previous BSDF sample (or seen directly) ----
            emitter = si.emitter(scene)
            has_emitter = emitter != None  # noqa: E711 -- drjit pointer comparison
            # hide_emitters: after the skip above, a camera ray's emitter can only be the environment.
            has_emitter &= ~(mi.Bool(hide_emitters) & (depth == 0))
            ds = mi.DirectionSample3f(scene, si, prev_si)
            em_pdf = dr.select(~prev_bsdf_delta,
                               scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta), 0.0)
            mis_bsdf = _mis_weight(prev_bsdf_pdf, em_pdf)
            Le = throughput * mis_bsdf * emitter.eval(si, active & has_emitter & (prev_bsdf_pdf > 0))
            L += Le
            L_diffuse += dr.select(diffuse_path & ~on_spec_chain, Le, 0.0)

            # ---- is this the feature vertex? ----
            material = si.shape.eval_attribute_3(MATERIAL_ATTRIBUTE, si, active & hit)
            ident = si.shape.eval_attribute_3(IDENT_ATTRIBUTE, si, active & hit)
            bsdf = si.bsdf(ray)
            bsdf_flags = bsdf.flags()
            is_specular = hit & (~mi.has_flag(bsdf_flags, mi.BSDFFlags.Smooth) | (ident.y > 0.5))
            active_next = active & (depth + 1 < self.max_depth) & hit
            # The chain ends here: at a non-specular vertex, a miss, or when the path stops.
            latch = active & on_spec_chain & (~is_specular | ~active_next)
            if latch:
                f_albedo = feature_albedo(bsdf, si, ident.z, hit)
                f_normal = mi.Normal3f(dr.select(hit, si.sh_frame.n, 0.0))
                f_position = mi.Point3f(dr.select(hit, si.p, 0.0))
                f_depth = path_length
                f_rough = dr.select(hit, material.x, 0.0)
                f_emissive = has_emitter
                f_metallic = hit & (material.y > 0.5)
                f_transmissive = refracted | (hit & (material.z > 0.5))
            if active & (depth == 0):
                f_spec_bounce = is_specular
            feature_vertex = latch & ~is_specular

            # ---- emitter sampling ----
            active_em = active_next & mi.has_flag(bsdf_flags, mi.BSDFFlags.Smooth)
            ds_em, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= ds_em.pdf != 0.0
            wo_em = si.to_local(ds_em.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo_em, active_em)
            mis_em = dr.select(ds_em.delta, 1.0, _mis_weight(ds_em.pdf, bsdf_pdf))
            L_em = dr.select(active_em, throughput * bsdf_val * em_weight * mis_em, 0.0)
            L += L_em
            if feature_vertex:
                bsdf_val_diffuse = bsdf.eval(ctx_diffuse, si, wo_em, active_em & feature_vertex)
                L_diffuse += dr.select(active_em,
                                       throughput * bsdf_val_diffuse * em_weight * mis_em, 0.0)
            L_diffuse += dr.select(diffuse_path & ~on_spec_chain & ~feature_vertex, L_em, 0.0)

            # ---- BSDF sampling ----
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
            if feature_vertex:
                diffuse_path = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
            if on_spec_chain & ~feature_vertex:
                refracted |= mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
            on_spec_chain &= ~latch

            ray = si.spawn_ray(si.to_world(bs.wo))
            throughput *= bsdf_weight
            eta *= bs.eta
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

            # ---- Russian roulette, as in Mitsuba's path integrator ----
            throughput_max = dr.max(throughput)
            rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d() < rr_prob
            throughput[rr_active] *= dr.rcp(rr_prob)
            active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)
            depth[hit] += 1

        aovs = [
            L_diffuse.x, L_diffuse.y, L_diffuse.z,
            f_albedo.x, f_albedo.y, f_albedo.z,
            f_normal.x, f_normal.y, f_normal.z,
            f_depth,
            f_rough,
            dr.select(f_emissive, 1.0, 0.0), dr.select(f_metallic, 1.0, 0.0),
            dr.select(f_transmissive, 1.0, 0.0), dr.select(f_spec_bounce, 1.0, 0.0),
            f_position.x, f_position.y, f_position.z,
        ]
        return L, depth != 0, aovs


mi.register_integrator("mcdn_features", lambda props: FeatureIntegrator(props))
