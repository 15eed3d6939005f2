"""Loading, validating and fingerprinting the harness configuration.

The JSON schema in workflow/schemas/config.schema.yaml is the single source of truth for the
keys, types, ranges and defaults; the Snakemake workflow validates against the same file. This
module adds readable error messages (key path plus allowed values) and the few cross-key
constraints that JSON Schema cannot express. Which scenes a config holds, and each scene's settings, is
:mod:`scenegen.catalog`.
"""

from __future__ import annotations

import copy
import difflib
import functools
import hashlib
import json
from collections.abc import Iterator, Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import jsonschema
import yaml

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "workflow" / "schemas" / "config.schema.yaml"

#: Upper bound on per-pixel sample layers (spp + extra_radiance_spp) of a noisy render.
MAX_SAMPLE_LAYERS = 32

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
