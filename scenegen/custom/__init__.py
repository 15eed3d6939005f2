"""Bring-your-own Mitsuba 3 XML scenes (config ``extra_scenes``), evaluated as ``custom_{name}``.

* :mod:`scenegen.custom.parse`: the XML read with Mitsuba's own parser, what the author asked for, what the
  harness renders instead (substitutions);
* :mod:`scenegen.custom.check`: the config-time checks (unsupported features, missing files) and the files whose
  contents enter the scene's digest;
* :mod:`scenegen.custom.scene`: the import job's manifest, camera paths, and each frame's Mitsuba scene.

Importing this package imports none of them (nor Mitsuba): the config checks and the render jobs import the
module they need.
"""
