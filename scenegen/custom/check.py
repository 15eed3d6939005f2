"""Bring-your-own scenes checked when the config is read: the XML parsed (no rendering), every plugin known,
every file it references present, unsupported features refused by name; and the files that make up a
scene, whose contents enter its digest.

What the harness can render is decided here, before any job runs (``custom_scene_problems``, called by the
workflow with the other config checks). The table of supported features is docs/custom-scenes.md; a
feature that would render wrongly is in ``UNSUPPORTED`` and refused with the reason.

A file reference is a ``filename`` property of any plugin (meshes: obj, ply, serialized; bitmap textures;
envmap; measured data), resolved as Mitsuba does: against the main XML's folder first, then the working
directory (``scenegen.custom.parse.xml_folder_on_resolver``). Parsing needs no Mitsuba variant to be set:
it uses ``scalar_rgb``'s parser, which knows the same plugins.
"""
from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scenegen.custom.parse import CustomSceneError, parse_state, xml_folder_on_resolver

#: Parser variant of the config-time checks (plugins are the same in every variant).
CHECK_VARIANT = "scalar_rgb"
#: Plugins (by parser object type and plugin name; None: any of that type) the feature integrator cannot render
#: as Mitsuba's ``path`` would, with the reason given to the user.
UNSUPPORTED: dict[tuple[str, str | None], str] = {
    ("Medium", None): ("participating media are not rendered by the harness's surface path tracer "
                       "(mcdn_features); bring volumes as volumes.extra (.npy fields) instead"),
    ("Shape", "shapegroup"): ("instancing (shapegroup / instance) is not supported: a loaded instance cannot be "
                              "placed in the per-frame scene the harness builds around its own camera; export "
                              "the instances as separate shapes"),
    ("Shape", "instance"): ("instancing (shapegroup / instance) is not supported: a loaded instance cannot be "
                            "placed in the per-frame scene the harness builds around its own camera; export the "
                            "instances as separate shapes"),
}


@dataclass(frozen=True)
class FileReference:
    """A ``filename`` property: the plugin that holds it, where (``file (line, col)``), the authored value and
    the resolved path (None when no file of that name exists)."""

    plugin: str
    location: str
    value: str
    path: Path | None


@dataclass(frozen=True)
class SceneCheck:
    """A custom scene as parsed at config time: its XML files (the main one first, then includes), the
    file references, and the problems found (empty when it can be rendered)."""

    xml_files: tuple[Path, ...]
    references: tuple[FileReference, ...]
    problems: tuple[str, ...]

    def files(self) -> list[Path]:
        """Every file the scene is made of: its XML files, then the referenced files, without repeats."""
        seen: dict[Path, None] = dict.fromkeys(self.xml_files)
        seen.update(dict.fromkeys(ref.path for ref in self.references if ref.path is not None))
        return list(seen)


_checks: dict[tuple, tuple[tuple, SceneCheck]] = {}   # (xml, params) -> (file states, check)


def _file_states(paths: list[Path]) -> tuple:
    """(path, mtime, size) of each path ((path,) when missing): a cached check is reused while they hold."""
    states = []
    for path in paths:
        try:
            stat = os.stat(path)
            states.append((str(path), stat.st_mtime_ns, stat.st_size))
        except OSError:
            states.append((str(path),))
    return tuple(states)


def check_scene(xml: Path, params: Mapping[str, Any] | None = None) -> SceneCheck:
    """Parse ``xml`` with ``params`` and check it (see the module docstring). A malformed XML or missing
    file is a problem, not an exception. Cached per process while no file involved changes (mtime, size)."""
    import mitsuba as mi

    xml = Path(xml).resolve()
    cache_key = (str(xml), tuple(sorted((params or {}).items(), key=str)))
    cached = _checks.get(cache_key)
    if cached is not None and cached[0] == _file_states([xml, *cached[1].files()]):
        return cached[1]
    try:
        _, state = parse_state(xml, params, variant=CHECK_VARIANT)
    except CustomSceneError as exc:
        return SceneCheck((xml,), (), (str(exc),))
    problems: list[str] = []
    references: list[FileReference] = []
    plugins = mi.PluginManager.instance()
    with xml_folder_on_resolver(xml) as resolver:
        for node in state.nodes:
            props = node.props
            plugin = props.plugin_name()
            location = mi.parser.file_location(state, node)
            kind = str(node.type).rpartition(".")[2]
            if plugin and kind != "Scene" and plugins.plugin_type(plugin) == mi.ObjectType.Unknown:
                problems.append(f"{location}: unknown plugin '{plugin}'")
                continue
            for (refused_kind, refused_plugin), why in UNSUPPORTED.items():
                if kind == refused_kind and refused_plugin in (None, plugin):
                    problems.append(f"{location}: {kind.lower()} '{plugin}' is not supported: {why}")
            if "filename" in props.keys() and props.type("filename") == mi.Properties.Type.String:
                value = str(props["filename"])
                resolved = Path(str(resolver.resolve(value)))
                path = resolved.resolve() if resolved.is_file() else None
                references.append(FileReference(plugin, location, value, path))
                if path is None:
                    problems.append(f"{location}: {plugin} file '{value}' not found (looked in "
                                    f"{xml.parent} and the working directory)")
    check = SceneCheck(tuple(Path(str(f)).resolve() for f in state.files) or (xml,), tuple(references),
                       tuple(problems))
    _checks[cache_key] = (_file_states([xml, *check.files()]), check)
    return check


def file_digests(check: SceneCheck, root: Path) -> dict[str, str]:
    """{path: SHA-256} of every file of a checked scene; paths relative to ``root`` (the main XML's folder)
    where they lie below it, else absolute. CustomSceneError if the scene has problems."""
    if check.problems:
        raise CustomSceneError("; ".join(check.problems))
    out = {}
    for path in check.files():
        name = str(path.relative_to(root)) if path.is_relative_to(root) else str(path)
        out[name] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def scene_files(entry: Mapping[str, Any]) -> dict[str, str]:
    """{path: SHA-256} of the XML of an extra_scenes ``entry`` and of every file it references (its digest
    covers them: an edited mesh or texture reruns the import). CustomSceneError naming the problems."""
    xml = Path(entry["xml"]).resolve()
    check = check_scene(xml, entry.get("params"))
    if check.problems:
        raise CustomSceneError(f"custom scene '{entry['name']}' ({xml}): " + "; ".join(check.problems))
    return file_digests(check, xml.parent)


def custom_scene_problems(cfg: Mapping[str, Any]) -> list[str]:
    """Config-time problems of every extra_scenes entry: each names the scene id, the file and the line."""
    problems = []
    for index, entry in enumerate(cfg.get("extra_scenes") or []):
        scene_id = f"custom_{entry['name']}"
        xml = Path(entry["xml"])
        if not xml.is_file():
            problems.append(f"extra_scenes[{index}] (scene {scene_id}): XML file not found: {xml.resolve()}")
            continue
        for problem in check_scene(xml, entry.get("params")).problems:
            problems.append(f"extra_scenes[{index}] (scene {scene_id}): {problem}")
    return problems
