"""The manual's generated pages (docs/, built by MkDocs through ``mkdocs_hooks.py``): the configuration
reference from the config's JSON schema, so the reference cannot drift from what the workflow validates."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
SCHEMA = REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml"
#: Pages of docs/ that exist only in the built site (mkdocs_hooks.py adds them).
CONFIG_REFERENCE_PAGE = "configuration-reference.md"


def _resolve(node: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    """``node`` with a local ``$ref`` (``#/$defs/name``) replaced by its definition (keys beside the ref kept)."""
    ref = node.get("$ref")
    if not ref:
        return node
    target: Any = schema
    for part in ref.removeprefix("#/").split("/"):
        target = target[part]
    return {**target, **{key: value for key, value in node.items() if key != "$ref"}}


def _type_text(node: dict[str, Any]) -> str:
    """The JSON type of ``node`` with its constraints, e.g. ``integer >= 1``, ``one of: path, features``."""
    if "enum" in node:
        return "one of: " + ", ".join(f"`{json.dumps(value)}`" for value in node["enum"])
    kind = node.get("type", "any")
    text = " or ".join(kind) if isinstance(kind, list) else str(kind)
    if "oneOf" in node or "anyOf" in node:
        options = node.get("oneOf") or node.get("anyOf")
        text = " or ".join(sorted({str(option.get("type", "object")) for option in options}))
    bounds = [f"{sign} {node[key]}" for key, sign in (("minimum", ">="), ("exclusiveMinimum", ">"),
                                                       ("maximum", "<="), ("exclusiveMaximum", "<")) if key in node]
    if node.get("minItems") is not None and node.get("minItems") == node.get("maxItems"):
        bounds.append(f"{node['minItems']} items")
    return text + (" " + ", ".join(bounds) if bounds else "")


def _rows(node: dict[str, Any], key: str, schema: dict[str, Any], required: bool) -> list[str]:
    """Table rows of ``node`` (config key ``key``) and, below it, of its properties and list items' properties."""
    node = _resolve(node, schema)
    default = f"`{json.dumps(node['default'])}`" if "default" in node else ("required" if required else "")
    description = " ".join(str(node.get("description", "")).split()).replace("|", "\\|")
    rows = [f"| `{key}` | {_type_text(node)} | {default} | {description} |"] if key else []
    for name, child in (node.get("properties") or {}).items():
        rows += _rows(child, f"{key}.{name}" if key else name, schema, name in node.get("required", []))
    items = node.get("items")
    if isinstance(items, dict) and (_resolve(items, schema).get("properties")):
        rows += _rows({**_resolve(items, schema), "description": ""}, f"{key}[]", schema, False)[1:]
    return rows


def config_reference(schema: dict[str, Any] | None = None) -> str:
    """Markdown page: every config key of ``schema`` (default: the workflow's) with type, default and meaning."""
    schema = schema if schema is not None else yaml.safe_load(SCHEMA.read_text())
    header = ["# Configuration reference", "",
              "Generated from `workflow/schemas/config.schema.yaml`, the schema every config is validated against "
              "(an unknown or misspelt key is an error). `key[]` is a field of each entry of list `key`. "
              "Constraints between keys are checked by `scenegen.config` and `denoisers.evaluate`.", "",
              " ".join(str(schema.get("description", "")).split()), "",
              "| key | type | default | meaning |", "|---|---|---|---|"]
    return "\n".join(header + _rows(schema, "", schema, False)) + "\n"
