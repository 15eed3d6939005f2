"""Loading, validating and fingerprinting the harness configuration.

The JSON schema in workflow/schemas/config.schema.yaml is the single source of truth for the
keys, types, ranges and defaults; the Snakemake workflow validates against the same file. This
module adds readable error messages (key path plus allowed values) and the few cross-key
constraints that JSON Schema cannot express.
"""

from __future__ import annotations

import copy
import difflib
import functools
import hashlib
import json
import math
from collections.abc import Iterator, Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import jsonschema
import yaml

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "workflow" / "schemas" / "config.schema.yaml"

#: Upper bound on per-pixel sample layers (spp + extra_radiance_spp) of a noisy render.
MAX_SAMPLE_LAYERS = 32

SCENE_SPLITS = ("train", "test")
CUSTOM_PREFIX = "custom_"
#: Scene ids of the stability scenarios (config section ``stability``, scenegen.scenarios): stab_{scenario}.
#: They are rendered and masked (target ``stability``), never trained on or evaluated by the evaluation rows.
STABILITY_PREFIX = "stab_"
#: Suffix of a scenario's failure-free control clip, stab_{name}__still (scenegen.scenarios.hold_final_frame):
#: rendered and denoised like its scenario, scored only as the steady state of the scenario's lag metric.
STABILITY_CONTROL_SUFFIX = "__still"
#: Scene ids of the volumetric clips (config section ``volumes``, scenegen.volumes.scenes):
#: vol_{split}_{scenario}_{index:03d}, split "test" or "train". Rendered with the volumetric integrators only.
VOLUME_PREFIX = "vol_"
VOLUME_SPLITS = ("test", "train")
#: Bring-your-own volumes (``volumes.extra``): vol_custom_{name}, evaluated like the vol_test_* clips.
VOLUME_CUSTOM_PREFIX = f"{VOLUME_PREFIX}custom_"
#: Scenes whose references render.train_reference_spp applies to (the training and validation scenes).
TRAIN_PREFIX = "train_"
TEST_PREFIX = "test_"
#: Scenes every method is scored on (render.test_reference_spp applies to them): seeded and external.
EVALUATED_PREFIXES = (TEST_PREFIX, CUSTOM_PREFIX)

#: What a workflow run writes below the config's ``output_dir`` (the experiment folder); `python -m
#: denoisers clean` removes exactly these entries, so another experiment nested inside the folder survives.
OUTPUT_ENTRIES: tuple[str, ...] = ("scenes", "renders", "models", "tuning", "denoised", "metrics", "robustness",
                                   "timing", "stability", "tables", "figures", "REPORT.md", "logs", "benchmarks",
                                   ".config")
#: Hex characters of the settings digests that outputs record (64 bits: no accidental collisions).
DIGEST_CHARS = 16


class ConfigError(ValueError):
    """Raised for an invalid configuration; the message names every offending key path."""


#: libyaml's parser when PyYAML was built with it (several times faster; the same SafeConstructor builds the
#: objects, so configs load to identical dicts and digests), else the pure-Python one.
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def yaml_load(text: str) -> Any:
    """``yaml.safe_load`` of ``text``, with libyaml's parser where available."""
    return yaml.load(text, Loader=_YAML_LOADER)


@functools.cache
def _parsed_schema(path: Path, mtime_ns: int) -> dict[str, Any]:
    return yaml_load(path.read_text(encoding="utf-8"))


def load_schema() -> dict[str, Any]:
    """Return a fresh copy of the config JSON schema (callers may mutate it). The file is parsed once
    per modification time: parsing the YAML costs ~0.3 s and config helpers ask for it often."""
    return copy.deepcopy(_parsed_schema(SCHEMA_PATH, SCHEMA_PATH.stat().st_mtime_ns))


@functools.cache
def _definition_validator(definition: str, mtime_ns: int) -> Any:
    return _DefaultFillingValidator(load_schema()["$defs"][definition])


def fill_definition_defaults(definition: str, value: Any) -> Any:
    """Validate ``value`` in place against ``$defs/<definition>`` of the schema, filling its defaults, and return
    it. The validator is built once per schema version (a deep copy of the schema per call cost ~5 ms, and
    model specs ask hundreds of times per job); the defaults it fills are copies, so ``value`` shares nothing
    with the schema."""
    _definition_validator(definition, SCHEMA_PATH.stat().st_mtime_ns).validate(value)
    return value


def _with_defaults(validator_class: type) -> type:
    """Extend a jsonschema validator class so that validation also fills in `default` values."""
    validate_properties = validator_class.VALIDATORS["properties"]

    def fill_defaults_then_validate(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for key, subschema in properties.items():
                if "default" in subschema and key not in instance:
                    # Deep copy: a shared mutable default would leak between configs.
                    instance[key] = copy.deepcopy(subschema["default"])
        yield from validate_properties(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": fill_defaults_then_validate})


_DefaultFillingValidator = _with_defaults(jsonschema.Draft202012Validator)


def format_key_path(path: Sequence[Any]) -> str:
    """Render a jsonschema path like ('extra_scenes', 0, 'name') as 'extra_scenes[0].name'."""
    text = ""
    for part in path:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text or "<top level>"


def _allowed_range(schema: dict[str, Any]) -> str:
    """Describe the numeric bounds of a schema node, e.g. '1..32' or '> 0'."""
    low, high = schema.get("minimum"), schema.get("maximum")
    if low is not None and high is not None:
        return f"{low}..{high}"
    parts = []
    if low is not None:
        parts.append(f">= {low}")
    if "exclusiveMinimum" in schema:
        parts.append(f"> {schema['exclusiveMinimum']}")
    if high is not None:
        parts.append(f"<= {high}")
    if "exclusiveMaximum" in schema:
        parts.append(f"< {schema['exclusiveMaximum']}")
    return " and ".join(parts)


# JSON Schema type names as a YAML author knows them.
_YAML_TYPE_NAMES = {"object": "mapping", "array": "list", "number": "number", "integer": "integer", "string": "string"}


def _describe_error(error: jsonschema.ValidationError) -> list[str]:
    """Turn one jsonschema error into messages naming the key path and what is allowed."""
    path = list(error.absolute_path)
    key = format_key_path(path)
    value = error.instance
    kind = error.validator
    subschema = error.schema if isinstance(error.schema, dict) else {}

    if kind == "additionalProperties":
        allowed = sorted(subschema.get("properties", {}))
        where = f"'{format_key_path(path)}'" if path else "the top level"
        messages = []
        for extra in sorted(set(value) - set(allowed)):
            hint = difflib.get_close_matches(str(extra), allowed, n=1)
            did_you_mean = f" (did you mean '{hint[0]}'?)" if hint else ""
            messages.append(
                f"unknown config key '{format_key_path([*path, extra])}'{did_you_mean}; "
                f"allowed keys in {where}: {', '.join(allowed)}"
            )
        return messages
    if kind == "required":
        missing = [name for name in error.validator_value if name not in value]
        return [f"missing required config key '{format_key_path([*path, name])}'" for name in missing]
    if kind == "enum":
        allowed = ", ".join(str(option) for option in error.validator_value)
        return [f"config key '{key}' = {value!r} is not allowed; allowed values: {allowed}"]
    if kind in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        return [f"config key '{key}' = {value!r} is out of range; allowed range: {_allowed_range(subschema)}"]
    if kind == "multipleOf":
        return [f"config key '{key}' = {value!r} must be a multiple of {error.validator_value}"]
    if kind == "type":
        types = error.validator_value if isinstance(error.validator_value, list) else [error.validator_value]
        expected = " or ".join(_YAML_TYPE_NAMES.get(name, name) for name in types)
        return [f"config key '{key}' = {value!r} has the wrong type; allowed type: {expected}"]
    if kind in ("minItems", "maxItems"):
        low, high = subschema.get("minItems", 0), subschema.get("maxItems")
        count = f"exactly {low}" if low == high else f"{low}..{high if high is not None else 'any'}"
        return [f"config key '{key}' = {value!r} has {len(value)} items; allowed: {count} items"]
    if kind == "pattern":
        return [f"config key '{key}' = {value!r} does not match the allowed pattern {error.validator_value}"]
    if kind == "oneOf" and all(set(option) == {"required"} for option in error.validator_value):
        options = [option["required"] for option in error.validator_value]
        names = [" + ".join(keys) for keys in options]
        given = [name for name, keys in zip(names, options) if all(k in value for k in keys)]
        return [f"config key '{key}' = {value!r} needs exactly one of {', '.join(names)}; "
                f"given: {', '.join(given) or 'none'}"]
    if kind == "uniqueItems":
        return [f"config key '{key}' = {value!r} contains duplicates; allowed: each value at most once"]
    return [f"config key '{key}': {error.message}"]


def _cross_key_problems(cfg: dict[str, Any]) -> Iterator[str]:
    """Constraints between keys that the JSON schema cannot express (assumes a schema-valid cfg)."""
    render, scenes = cfg["render"], cfg["scenes"]
    layers = render["spp"] + render["extra_radiance_spp"]
    if layers > MAX_SAMPLE_LAYERS:
        yield (
            f"config keys 'render.spp' + 'render.extra_radiance_spp' = {layers} is out of range; "
            f"allowed: spp + extra_radiance_spp <= {MAX_SAMPLE_LAYERS}"
        )
    low, high = scenes["objects"]
    if low > high:
        yield f"config key 'scenes.objects' = {scenes['objects']!r} is invalid; allowed: [min, max] with min <= max"
    low, high = scenes["luminance_range"]
    if low >= high:
        yield (
            f"config key 'scenes.luminance_range' = {scenes['luminance_range']!r} is invalid; "
            "allowed: [low, high] with 0 < low < high"
        )
    warmup = int((cfg.get("evaluation") or {}).get("warmup_frames", 0))
    if scenes["frames"] <= warmup:
        yield (f"config key 'scenes.frames' = {scenes['frames']} leaves no frame after the "
               f"evaluation.warmup_frames = {warmup} warm-up frames; allowed: more than {warmup}")
    device = (cfg.get("compute") or {}).get("device", "auto")
    if render["variant"].startswith("cuda") and device == "cpu":
        yield (f"config key 'render.variant' = {render['variant']!r} needs compute.device cuda, but it is cpu; "
               "allowed: llvm_ad_rgb or scalar_rgb on the CPU (llvm_ad_rgb runs as cuda_ad_rgb under "
               "compute.device cuda)")
    stability = cfg.get("stability") or {}
    if stability.get("spp") is not None and stability["spp"] + render["extra_radiance_spp"] > MAX_SAMPLE_LAYERS:
        yield (f"config keys 'stability.spp' + 'render.extra_radiance_spp' = "
               f"{stability['spp'] + render['extra_radiance_spp']} is out of range; allowed: <= {MAX_SAMPLE_LAYERS}")
    for index, entry in enumerate(cfg["extra_scenes"]):
        if entry.get("max_depth") == 0:
            yield (f"config key 'extra_scenes[{index}].max_depth' = 0 is not allowed; allowed: -1 (no limit) "
                   "or 1..1024")
    names = [entry["name"] for entry in cfg["extra_scenes"]]
    for name in sorted({name for name in names if names.count(name) > 1}):
        yield f"config key 'extra_scenes' has the name {name!r} more than once; allowed: unique names"
    extra_names = [entry["name"] for entry in (cfg.get("volumes") or {}).get("extra", [])]
    for name in sorted({name for name in extra_names if extra_names.count(name) > 1}):
        yield f"config key 'volumes.extra' has the name {name!r} more than once; allowed: unique names"
    yield from _output_dir_problems(cfg.get("output_dir", "results"))


def _output_dir_problems(value: str) -> Iterator[str]:
    """An experiment folder must be a folder of its own: not the working directory or the file system root,
    not above them ('..'), and (if relative) not inside another experiment's output folders, which that
    experiment's clean would remove."""
    parts = PurePosixPath(value).parts
    allowed = "allowed: a folder of its own, e.g. results or results/smoke (relative or absolute, no '..')"
    if not parts or parts in ((".",), ("/",)) or ".." in parts:
        yield f"config key 'output_dir' = {value!r} is not allowed; {allowed}"
    # Relative paths only: an absolute path like /data/renders/exp1 is not inside an experiment of this tree.
    clash = [part for part in parts if part in OUTPUT_ENTRIES] if not PurePosixPath(value).is_absolute() else []
    if clash:
        yield (f"config key 'output_dir' = {value!r} has a component {clash[0]!r}, a folder of the experiment "
               f"layout ({', '.join(OUTPUT_ENTRIES)}); {allowed}")


def output_root(cfg: dict[str, Any]) -> Path:
    """The experiment folder of a validated config (key ``output_dir``), normalised (no trailing slash)."""
    return Path(cfg["output_dir"])


def short_digest(digest: str) -> str:
    """The recorded form of a SHA-256 hex digest: its first DIGEST_CHARS characters."""
    return digest[:DIGEST_CHARS]


def config_problems(cfg: Any) -> list[str]:
    """Validate `cfg` in place (filling defaults) and return readable problems; empty when valid."""
    validator = _DefaultFillingValidator(load_schema())
    errors = sorted(validator.iter_errors(cfg), key=lambda err: [str(part) for part in err.absolute_path])
    # dict.fromkeys: jsonschema reports one error per missing key, each describing all of them.
    problems = list(dict.fromkeys(message for error in errors for message in _describe_error(error)))
    if not problems:
        problems = list(_cross_key_problems(cfg))
    return problems


def validate_config(cfg: dict[str, Any]) -> dict[str, Any]:
    """Validate `cfg` in place, fill defaults and return it; raise ConfigError listing all problems."""
    problems = config_problems(cfg)
    if problems:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))
    return cfg


def load_config(path: str | Path) -> dict[str, Any]:
    """Load a YAML config file, validate it against the schema and return it with defaults filled."""
    cfg = read_config_file(path)
    try:
        return validate_config(cfg)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A YAML config file's mapping as written (not validated); a ConfigError naming the file if it cannot be read,
    is not YAML or is not a mapping."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot read config file {path}: {err}") from err
    try:
        cfg = yaml_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {path} is not valid YAML: {err}") from err
    if not isinstance(cfg, dict):
        raise ConfigError(f"config file {path} must contain a mapping of keys, got {type(cfg).__name__}")
    return cfg


def _lookup(cfg: dict[str, Any], dotted_key: str) -> Any:
    node: Any = cfg
    for part in dotted_key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(f"config has no key '{dotted_key}'")
        node = node[part]
    return node


def config_digest(cfg: dict[str, Any], *sections: str) -> str:
    """SHA-256 hex digest of the canonical JSON of the given config sections.

    `sections` are dotted key paths ('seed', 'render', 'scenes.frames'); with none, the whole
    config is hashed. Key order in the YAML does not matter.
    """
    selected = {section: _lookup(cfg, section) for section in sections} if sections else cfg
    canonical = json.dumps(selected, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def extra_scene(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """Return the extra_scenes entry of a custom_{name} scene id; KeyError if there is none."""
    if not scene_id.startswith(CUSTOM_PREFIX):
        raise KeyError(f"{scene_id!r} is not a custom scene id")
    name = scene_id[len(CUSTOM_PREFIX) :]
    for entry in cfg.get("extra_scenes", []):
        if entry["name"] == name:
            return entry
    raise KeyError(f"no extra_scenes entry named {name!r} (scene id {scene_id!r})")


def scene_ids(cfg: dict[str, Any]) -> list[str]:
    """All scene ids: train_000.., test_000.., then custom_{name} for every extra scene."""
    ids = [f"{split}_{index:03d}" for split in SCENE_SPLITS for index in range(cfg["scenes"][f"n_{split}"])]
    ids += [f"{CUSTOM_PREFIX}{entry['name']}" for entry in cfg.get("extra_scenes", [])]
    return ids


def stability_scene_ids(cfg: dict[str, Any]) -> list[str]:
    """Scene ids of the stability scenarios, stab_{name} for every ``stability.scenarios`` entry in config
    order; empty when ``stability.enabled`` is false. Not part of scene_ids (never trained on or evaluated)."""
    stability = cfg.get("stability") or {}
    if not stability.get("enabled", False):
        return []
    return [f"{STABILITY_PREFIX}{name}" for name in stability.get("scenarios", [])]


def stability_control_id(scene_id: str) -> str:
    """The failure-free control clip's id of stability scene ``scene_id``: stab_{name}__still."""
    return f"{scene_id}{STABILITY_CONTROL_SUFFIX}"


def stability_scenario(cfg: dict[str, Any], scene_id: str) -> str:
    """Scenario name of a stab_{name} scene id or of its control stab_{name}__still; KeyError if the config
    does not have the scenario."""
    scene_id = scene_id.removesuffix(STABILITY_CONTROL_SUFFIX)
    if scene_id not in stability_scene_ids(cfg):
        raise KeyError(f"{scene_id!r} is not a stability scene of this config (stability.enabled, "
                       f"stability.scenarios: {', '.join(stability_scene_ids(cfg)) or 'none'})")
    return scene_id[len(STABILITY_PREFIX):]


def volume_scene_ids(cfg: dict[str, Any]) -> list[str]:
    """Scene ids of the volumetric clips: for each split (test, then train) and each ``volumes.scenarios``
    kind in config order, vol_{split}_{scenario}_{index:03d}; empty when ``volumes.enabled`` is false. Not
    part of scene_ids (the surface scenes' split, training and evaluation never see them)."""
    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return []
    return [f"{VOLUME_PREFIX}{split}_{scenario}_{index:03d}" for split in VOLUME_SPLITS
            for scenario in volumes.get("scenarios", []) for index in range(int(volumes.get(f"n_{split}", 0)))] + [
        f"{VOLUME_CUSTOM_PREFIX}{entry['name']}" for entry in volumes.get("extra", [])]


def volume_extra(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """The ``volumes.extra`` entry of a vol_custom_{name} scene id; KeyError otherwise."""
    name = scene_id[len(VOLUME_CUSTOM_PREFIX):]
    for entry in (cfg.get("volumes") or {}).get("extra", []):
        if entry["name"] == name:
            return entry
    raise KeyError(f"no volumes.extra entry named {name!r} (scene id {scene_id!r})")


def volume_clip_spec(cfg: dict[str, Any], scene_id: str) -> tuple[str, str, int]:
    """(split, scenario, index) of a vol_* scene id (a vol_custom_* clip: ('custom', its scenario, 0)); KeyError if
    the config does not have it."""
    if scene_id not in volume_scene_ids(cfg):
        raise KeyError(f"{scene_id!r} is not a volumetric clip of this config (volumes.enabled, volumes.scenarios, "
                       f"volumes.n_test, volumes.n_train, volumes.extra: {', '.join(volume_scene_ids(cfg)) or 'none'})")
    if scene_id.startswith(VOLUME_CUSTOM_PREFIX):
        return "custom", volume_extra(cfg, scene_id).get("scenario", "camera"), 0
    split, rest = scene_id[len(VOLUME_PREFIX):].split("_", 1)
    scenario, index = rest.rsplit("_", 1)
    return split, scenario, int(index)


def volume_training_split(cfg: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(clips that train, validation clips) of the volumetric training clips: vol_train_* ordered index-major
    (index 0 of every scenario, then index 1, ...), the last ``training.validation_scenes`` (default 2) held out,
    so the held-out clips cover the scenarios."""
    volumes = cfg.get("volumes") or {}
    if not volumes.get("enabled", False):
        return [], []
    ids = [f"{VOLUME_PREFIX}train_{scenario}_{index:03d}" for index in range(int(volumes.get("n_train", 0)))
           for scenario in volumes.get("scenarios", [])]
    held_out = min(int((cfg.get("training") or {}).get("validation_scenes", 2)), len(ids))
    return ids[:len(ids) - held_out], ids[len(ids) - held_out:]


def scene_render_config(cfg: dict[str, Any], scene_id: str) -> dict[str, Any]:
    """The ``render`` settings a scene is rendered with: ``render`` itself, except for the stability scenes,
    whose width, height, spp and reference_spp come from the ``stability`` section (spp null = render.spp),
    and whose references always hold the feature means (their texture masks read the reference albedo), and
    the volumetric clips, whose size, spp, reference spp and path depth come from the ``volumes`` section (no
    radiance-only layers; references with Mitsuba's volpath, radiance only)."""
    if scene_id.startswith(VOLUME_PREFIX):
        volumes = cfg["volumes"]
        spp = volumes["spp"] if volumes.get("spp") is not None else cfg["render"]["spp"]
        return {**cfg["render"], "width": volumes["width"], "height": volumes["height"], "spp": spp,
                "extra_radiance_spp": 0, "reference_spp": volumes["reference_spp"], "train_reference_spp": None,
                "test_reference_spp": None,
                "reference_integrator": "path", "max_depth": volumes["max_depth"]}
    if not scene_id.startswith(STABILITY_PREFIX):
        return cfg["render"]
    stability = cfg["stability"]
    spp = stability["spp"] if stability.get("spp") is not None else cfg["render"]["spp"]
    return {**cfg["render"], "width": stability["width"], "height": stability["height"], "spp": spp,
            "reference_spp": stability["reference_spp"], "train_reference_spp": None, "test_reference_spp": None,
            "reference_integrator": "features"}


def training_scene_split(cfg: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(scenes that train, validation scenes): the train_* ids with the last ``training.validation_scenes``
    (default 2) held out for validation."""
    train = [scene for scene in scene_ids(cfg) if scene.startswith(TRAIN_PREFIX)]
    held_out = min(int((cfg.get("training") or {}).get("validation_scenes", 2)), len(train))
    return train[:len(train) - held_out], train[len(train) - held_out:]


def scene_reference_spp(cfg: dict[str, Any], scene_id: str) -> int:
    """Reference spp of a scene: ``render.train_reference_spp`` for the train_* scenes that train and
    ``render.test_reference_spp_per_scene[scene]``, else ``render.test_reference_spp``, for the evaluated test_*
    and custom_* scenes, each when set (not null), else
    ``render.reference_spp`` (always for the held-out validation scenes, whose references select every model)."""
    if scene_id.startswith((STABILITY_PREFIX, VOLUME_PREFIX)):
        return int(scene_render_config(cfg, scene_id)["reference_spp"])
    render = cfg["render"]
    train_spp = render.get("train_reference_spp")
    if train_spp is not None and scene_id in training_scene_split(cfg)[0]:
        return int(train_spp)
    if scene_id.startswith(EVALUATED_PREFIXES):
        per_scene = render.get("test_reference_spp_per_scene") or {}
        return int(per_scene[scene_id]) if scene_id in per_scene else evaluated_reference_spp(cfg)
    return int(render["reference_spp"])


def evaluated_reference_spp(cfg: dict[str, Any]) -> int:
    """Reference spp of the evaluated test_* and custom_* scenes: ``render.test_reference_spp``, else
    ``render.reference_spp``."""
    test_spp = cfg["render"].get("test_reference_spp")
    return int(test_spp if test_spp is not None else cfg["render"]["reference_spp"])


def reference_spp_exceptions(cfg: dict[str, Any]) -> dict[str, int]:
    """The evaluated scenes of ``cfg`` whose references have their own spp (render.test_reference_spp_per_scene,
    names the config has no scene of left out): {scene id: spp}, sorted by id."""
    per_scene = cfg["render"].get("test_reference_spp_per_scene") or {}
    if not per_scene:
        return {}
    present = set(scene_ids(cfg))
    return {scene: int(spp) for scene, spp in sorted(per_scene.items()) if scene in present}


def evaluated_reference_text(cfg: dict[str, Any]) -> str:
    """'3072 spp' or '3072 spp (test_001: 6144)': the evaluated scenes' reference spp for reports."""
    exceptions = reference_spp_exceptions(cfg)
    extra = ", ".join(f"{scene}: {spp}" for scene, spp in exceptions.items())
    return f"{evaluated_reference_spp(cfg)} spp" + (f" ({extra})" if extra else "")


def scene_frame_count(cfg: dict[str, Any], scene_id: str) -> int:
    """Frames in the clip of a scene (the extra scene's own count for custom scenes; ``scenes.train_frames``,
    when set, for the train_* scenes)."""
    if scene_id.startswith(CUSTOM_PREFIX):
        return int(extra_scene(cfg, scene_id)["frames"])
    if scene_id.startswith(STABILITY_PREFIX):
        return int(cfg["stability"]["frames"])
    if scene_id.startswith(VOLUME_PREFIX):
        return int(cfg["volumes"]["frames"])
    if scene_id.startswith(TRAIN_PREFIX) and cfg["scenes"].get("train_frames") is not None:
        return int(cfg["scenes"]["train_frames"])
    return int(cfg["scenes"]["frames"])


def scene_frames_per_chunk(cfg: dict[str, Any], scene_id: str) -> int:
    """Frames per render job of a scene: ``scenes.frames_per_chunk``; a stability or volumetric clip is one chunk."""
    if scene_id.startswith((STABILITY_PREFIX, VOLUME_PREFIX)):
        return scene_frame_count(cfg, scene_id)
    return int(cfg["scenes"]["frames_per_chunk"])


def chunk_count(cfg: dict[str, Any], scene_id: str) -> int:
    """Number of render chunks of a scene: ceil(frames / frames_per_chunk)."""
    return math.ceil(scene_frame_count(cfg, scene_id) / scene_frames_per_chunk(cfg, scene_id))


def chunk_frames(cfg: dict[str, Any], scene_id: str, chunk: int) -> range:
    """Frame indices rendered by one chunk (the last chunk may be shorter)."""
    if not 0 <= chunk < chunk_count(cfg, scene_id):
        raise ValueError(f"scene {scene_id!r} has no chunk {chunk} (it has {chunk_count(cfg, scene_id)})")
    per_chunk = scene_frames_per_chunk(cfg, scene_id)
    return range(chunk * per_chunk, min((chunk + 1) * per_chunk, scene_frame_count(cfg, scene_id)))
