"""Command-line config overrides: ``snakemake --config 'render={spp: 8}'``.

Snakemake merges a nested ``--config`` value into the config file's dict but leaves the leaves of a
nested value as strings (``{spp: 8}`` gives ``{"spp": "8"}``), which the schema then rejects. Where the
schema expects a non-string type, :func:`coerce_override_strings` parses such a string as YAML and keeps
the result when its type fits. (Dotted keys such as ``render.spp=8`` are refused by Snakemake itself
before any project code runs; docs/model-store.md shows the nested form.)
"""
from __future__ import annotations

from typing import Any

import yaml

_PYTHON_TYPES: dict[str, tuple[type, ...]] = {
    "integer": (int,), "number": (int, float), "boolean": (bool,), "array": (list,), "object": (dict,),
    "null": (type(None),),
}


def _fits(value: Any, types: list[str]) -> bool:
    for name in types:
        allowed = _PYTHON_TYPES.get(name)
        if allowed and isinstance(value, allowed) and not (name in ("integer", "number") and isinstance(value, bool)):
            return True
    return False


def _coerce(value: Any, schema: dict) -> Any:
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        for key, item in list(value.items()):
            sub = properties.get(key, extra if isinstance(extra, dict) else {})
            value[key] = _coerce(item, sub)
        return value
    if isinstance(value, list):
        items = schema.get("items", {})
        return [_coerce(item, items) if isinstance(items, dict) else item for item in value]
    if isinstance(value, str):
        types = schema.get("type")
        types = [types] if isinstance(types, str) else list(types or [])
        if types and "string" not in types:
            try:
                parsed = yaml.safe_load(value)
            except yaml.YAMLError:
                return value
            if _fits(parsed, types):
                return _coerce(parsed, schema) if isinstance(parsed, (dict, list)) else parsed
    return value


def coerce_override_strings(config: dict, schema: dict) -> dict:
    """Parse string leaves of ``config`` where ``schema`` expects another type (in place; returns it)."""
    return _coerce(config, schema)
