"""Volumetric clips (Iglesias-Guitian et al. 2022): heterogeneous media, their scalar fields and transfer
functions, the scenes that hold them, and how they are rendered.

* :mod:`scenegen.volumes.media`: transfer functions and the Mitsuba medium box (``heterogeneous`` medium);
* :mod:`scenegen.volumes.fields`: procedural scalar fields and user ``.npy`` fields;
* :mod:`scenegen.volumes.mesh`: scalar fields from the shells of a mesh;
* :mod:`scenegen.volumes.scenes`: the scenarios (camera, light, transfer function) as scene dicts;
* :mod:`scenegen.volumes.framing`, :mod:`scenegen.volumes.motion`: camera framing and animation of a clip;
* :mod:`scenegen.volumes.integrator`: the per-sample volumetric integrator with its auxiliary buffers;
* :mod:`scenegen.volumes.render`: a clip's noisy and reference renders.

Surface scenes never import this package (a surface scene does not pay for volumes).
"""
