"""Reading a bring-your-own Mitsuba 3 XML scene with Mitsuba's own parser (``mi.parser``).

``parse_xml`` keeps every authored shape a shape of its own (Mitsuba's mesh merging off, ``merge``
shapes replaced by their children) and names the unnamed ones, so instantiated shapes can be
matched to their authored position. ``authored_settings`` reads what the author asked for (the
integrator's ``max_depth`` / ``rr_depth`` / ``hide_emitters``, film size, pixel filter, sampler,
sensor); ``render_settings`` is what the harness renders with and ``substitutions`` lists every
replacement it has to make, each as {what, authored, used, why}.

Relative paths resolve as ``mi.load_file`` resolves them: the XML's own folder is on Mitsuba's file
resolver while it is parsed *and* instantiated (``xml_folder_on_resolver``), so ``meshes/x.obj`` of a
downloaded scene folder loads wherever the harness runs; an ``<include>`` is found beside the file that
includes it, and the paths inside it resolve against the main XML's folder, as Mitsuba does.
``<default name=... value=.../>`` parameters take the values of the extra_scenes entry's ``params``.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Shape plugins that hold other shapes rather than being one.
SHAPE_CONTAINERS = ("merge", "shapegroup", "instance")
#: Id given to unnamed shape nodes (``{ID_PREFIX}{authored index:03d}``) to find them after loading.
ID_PREFIX = "_mcdn_shape_"
#: Defaults of Mitsuba's ``path`` integrator (and of every Monte Carlo integrator) for absent properties.
PATH_DEFAULTS: dict[str, Any] = {"max_depth": -1, "rr_depth": 5, "hide_emitters": False}
#: A box filter of this radius (pixels) covers exactly one pixel: the filter the sample layers use.
BOX_RADIUS = 0.5
_CLASS_SUFFIXES = ("Camera", "Filter", "Sampler")


class CustomSceneError(ValueError):
    """A custom scene's XML cannot be used; the message names the file."""


@dataclass
class ParsedXml:
    """A parsed XML scene: Mitsuba's parser config and state, and its authored shapes in document
    order as (node id, manifest name, plugin name)."""

    path: Path
    config: Any
    state: Any
    shapes: list[tuple[str, str, str]]
    shape_nodes: list[int]
    params: dict[str, str]

    def nodes_of(self, object_type: str) -> list[Any]:
        """Parser nodes of one mi.ObjectType name ('Integrator', 'Film', ...) in document order."""
        import mitsuba as mi

        wanted = getattr(mi.ObjectType, object_type)
        return [node for node in self.state.nodes if node.type == wanted]

    def set_texture_attributes(self, index: int, rows: dict[str, list[float]]) -> None:
        """Give authored shape ``index`` constant texture attributes {name: 3 floats} (evaluated by
        ``Shape.eval_attribute_3`` like mesh attributes; unbounded so ids above 1 survive)."""
        import mitsuba as mi

        props = self.state.nodes[self.shape_nodes[index]].props
        for name, row in rows.items():
            props[name] = mi.load_dict({"type": "srgb", "color": [float(v) for v in row], "unbounded": True})

    def instantiate(self):
        """The mi.Scene of the parsed state (consumes the state: parse again for another copy)."""
        import mitsuba as mi

        try:
            with xml_folder_on_resolver(self.path):
                mi.parser.transform_all(self.config, self.state)
                return mi.parser.instantiate(self.config, self.state)
        except Exception as exc:  # noqa: BLE001 -- Mitsuba raises RuntimeError with parser details
            raise CustomSceneError(f"cannot load custom scene XML {self.path}: {exc}") from exc


@contextlib.contextmanager
def xml_folder_on_resolver(xml: Path) -> Iterator[Any]:
    """Put ``xml``'s folder first on Mitsuba's file resolver (of this thread) for the ``with`` block, as
    ``mi.load_file`` does; yields the resolver. The resolver's previous search path is restored."""
    import mitsuba as mi

    resolver = mi.file_resolver()
    before = [str(resolver[i]) for i in range(len(resolver))]
    resolver.prepend(str(Path(xml).resolve().parent))
    try:
        yield resolver
    finally:
        resolver.clear()
        for folder in before:
            resolver.append(folder)


def parser_params(params: Mapping[str, Any] | None) -> dict[str, str]:
    """The extra_scenes entry's ``params`` as the parser's ``$name`` substitutions (strings; booleans as
    Mitsuba writes them)."""
    return {str(name): (str(value).lower() if isinstance(value, bool) else str(value))
            for name, value in (params or {}).items()}


def _references(props) -> list[tuple[str, Any]]:
    import mitsuba as mi

    return [(key, props[key]) for key in props.keys() if isinstance(props[key], mi.Properties.ResolvedReference)]


def _flatten_merges(state) -> None:
    """Replace every reference to a ``merge`` shape by references to its (recursively flattened)
    children: the shapes render the same, but stay separate shapes with separate ids."""
    import mitsuba as mi

    merges = {i for i, node in enumerate(state.nodes)
              if node.type == mi.ObjectType.Shape and node.props.plugin_name() == "merge"}

    def children(index: int) -> list[Any]:
        found = []
        for _, ref in _references(state.nodes[index].props):
            found += children(ref.index()) if ref.index() in merges else [ref]
        return found

    for index, node in enumerate(state.nodes):
        if index in merges:
            continue
        for key, ref in _references(node.props):
            if ref.index() in merges:
                del node.props[key]
                for number, child in enumerate(children(ref.index())):
                    node.props[f"{key}_merged_{number}"] = child


def parse_state(path: Path, params: Mapping[str, Any] | None = None, variant: str | None = None) -> tuple[Any, Any]:
    """Mitsuba's parser (config, state) of ``path`` with ``params`` for its ``$name`` defaults, mesh merging
    off, the XML's folder on the resolver. ``variant`` defaults to the active one (parsing needs none set:
    the config-time checks parse with ``scalar_rgb`` without selecting it). CustomSceneError naming the file
    (Mitsuba's message carries the line of a malformed XML)."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise CustomSceneError(f"custom scene XML not found: {path}")
    config = mi.parser.ParserConfig(variant or mi.variant())
    config.merge_meshes = False
    config.merge_equivalent = False
    try:
        with xml_folder_on_resolver(path):
            state = mi.parser.parse_file(config, str(path), **parser_params(params))
    except Exception as exc:  # noqa: BLE001 -- Mitsuba raises RuntimeError with parser details
        raise CustomSceneError(f"cannot load custom scene XML {path}: {exc}") from exc
    return config, state


def parse_xml(path: Path, params: Mapping[str, Any] | None = None) -> ParsedXml:
    """Parse ``path`` (parse_state) without mesh merging, undo ``merge`` shapes and name unnamed shapes."""
    import mitsuba as mi

    path = Path(path)
    config, state = parse_state(path, params)
    _flatten_merges(state)
    shapes, nodes = [], []
    for index, node in enumerate(state.nodes):
        plugin = node.props.plugin_name()
        if node.type != mi.ObjectType.Shape or plugin in SHAPE_CONTAINERS:
            continue
        authored_id = node.props.id()
        if not authored_id:
            node.props.set_id(f"{ID_PREFIX}{len(shapes):03d}")
        shapes.append((node.props.id(), authored_id or f"shape_{len(shapes):03d}", plugin))
        nodes.append(index)
    return ParsedXml(path, config, state, shapes, nodes, parser_params(params))


def _plugin(nodes: list[Any], instance: Any) -> tuple[str, bool]:
    """(plugin name, written in the XML): the first parser node's, else the loaded object's class."""
    if nodes:
        return nodes[0].props.plugin_name(), True
    name = instance.class_name()
    for suffix in _CLASS_SUFFIXES:
        name = name.removesuffix(suffix)
    return name.lower(), False


def authored_settings(parsed: ParsedXml, scene) -> dict[str, Any]:
    """What the XML asks for: integrator (None if absent) with max_depth, rr_depth, hide_emitters (the
    first integrator that sets each, else path's defaults), and of the first sensor: its type, film
    size and crop, pixel filter (name, radius in pixels, whether written or the film's default),
    sampler and sample count."""
    integrators = parsed.nodes_of("Integrator")
    authored: dict[str, Any] = {"integrator": integrators[0].props.plugin_name() if integrators else None}
    for key, default in PATH_DEFAULTS.items():
        source = next((node for node in integrators if key in node.props), None)
        authored[key] = type(default)(source.props[key]) if source is not None else default
    sensors = scene.sensors()
    authored["n_sensors"] = len(sensors)
    if sensors:
        film = sensors[0].film()
        authored["sensor"] = _plugin(parsed.nodes_of("Sensor"), sensors[0])[0]
        authored["width"], authored["height"] = (int(v) for v in film.size())
        authored["crop"] = [int(v) for v in film.crop_size()]
        authored["filter"], authored["filter_written"] = _plugin(parsed.nodes_of("ReconstructionFilter"),
                                                                 film.rfilter())
        authored["filter_radius"] = float(film.rfilter().radius())
        authored["sampler"] = _plugin(parsed.nodes_of("Sampler"), sensors[0].sampler())[0]
        authored["sample_count"] = int(sensors[0].sampler().sample_count())
    return authored


def render_settings(authored: dict[str, Any], entry: dict[str, Any]) -> dict[str, Any]:
    """What the harness renders with: max_depth / rr_depth from the extra_scenes entry if it sets them,
    else as authored (-1 = no limit); hide_emitters as authored; always the one-pixel box filter."""
    return {"max_depth": int(entry.get("max_depth", authored["max_depth"])),
            "rr_depth": int(entry.get("rr_depth", authored["rr_depth"])),
            "hide_emitters": bool(authored["hide_emitters"]), "filter": "box"}


def _row(what: str, authored: Any, used: Any, why: str) -> dict[str, str]:
    return {"what": what, "authored": str(authored), "used": str(used), "why": why}


def substitutions(authored: dict[str, Any], entry: dict[str, Any]) -> list[dict[str, str]]:
    """Every way the render differs from the XML as authored (see the module docstring)."""
    integrator = authored["integrator"]
    if integrator == "path":
        why = ("the harness's path tracer: the same estimator as path (MIS, Russian roulette, max_depth "
               "counted alike, hide_emitters honoured) that also returns the per-sample feature buffers")
    elif integrator is None:
        why = ("the XML names no integrator (mi.render needs one); path's defaults apply: max_depth -1 "
               "(no limit), rr_depth 5")
    else:
        why = (f"the light transport of '{integrator}' is not reproduced: the dataset needs the per-sample "
               "features of mcdn_features, a unidirectional surface path tracer like path (no participating media)")
    rows = [_row("integrator", integrator or "none", "mcdn_features", why)]
    for key in ("max_depth", "rr_depth"):
        if key in entry and int(entry[key]) != authored[key]:
            rows.append(_row(key, authored[key], entry[key], f"set by the extra_scenes entry's {key}"))
    if "sensor" not in authored:
        return rows + [_row("sensor", "none", "perspective (pinhole)", "the XML has no sensor; the extra_scenes "
                            "entry's camera (origin, target, fov_deg) places a pinhole camera")]
    filter_text = f"{authored['filter']} (radius {authored['filter_radius']:g} px" + \
        ("" if authored["filter_written"] else ", the film's default") + ")"
    if authored["filter"] != "box" or authored["filter_radius"] > BOX_RADIUS + 1e-6:
        rows.append(_row("pixel filter", filter_text, f"box (radius {BOX_RADIUS:g} px)",
                         "every pixel of a sample layer holds one independent sample, uniformly jittered in the "
                         "pixel; a filter reaching beyond the pixel would spread each sample over its neighbours "
                         "and correlate them, so noisy layers and references use the one-pixel box"))
    size = f"{authored['width']}x{authored['height']}"
    if authored["crop"] != [authored["width"], authored["height"]]:
        size += f" (crop {authored['crop'][0]}x{authored['crop'][1]})"
    rows.append(_row("resolution", size, "render.width x render.height of the config",
                     "every clip of a run has the config's resolution (methods, metrics and report assume one)"))
    rows.append(_row("sampler", f"{authored['sampler']}, {authored['sample_count']} spp",
                     "independent 1-spp layers (render.spp + render.extra_radiance_spp); references of "
                     "render.reference_spp in two halves", "the dataset stores every sample separately"))
    if authored["sensor"] != "perspective":
        rows.append(_row("sensor", authored["sensor"], "perspective (pinhole)",
                         "camera paths and motion vectors assume a pinhole camera"))
    if authored["n_sensors"] > 1:
        rows.append(_row("sensors", f"{authored['n_sensors']} sensors", "the first", "one camera per clip"))
    camera = entry["camera"]
    set_by_entry = [key for key in ("origin", "target", "fov_deg") if key in camera]
    rows.append(_row("camera", "static sensor", f"'{camera['path']}' camera path"
                     + (f" (entry sets {', '.join(set_by_entry)})" if set_by_entry else " from the sensor's pose"),
                     "clips are animated by the extra_scenes entry's camera"))
    return rows
