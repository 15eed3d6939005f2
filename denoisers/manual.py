"""The manual's generated pages (docs/, built by MkDocs through ``mkdocs_hooks.py``): the configuration
reference from the config's JSON schema, so the reference cannot drift from what the workflow validates, and one
page per reproduced paper from the published run."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
SCHEMA = REPO_ROOT / "workflow" / "schemas" / "config.schema.yaml"
#: Pages of docs/ that exist only in the built site (mkdocs_hooks.py adds them).
CONFIG_REFERENCE_PAGE = "configuration-reference.md"
#: The generated page of the Isik run's trainings, read from the committed store (denoisers.store.progress).
ISIK_TRAINING_PAGE = "isik2021-training.md"
ISIK_CONFIG = "config/isik2021.yaml"


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


# ------------------------------------------------------------------------------------------ paper pages
#: The published run the paper pages are generated from, and the folder of the site that holds them.
PAPERS_RUN = "runs/default"
PAPERS_DIR = "papers"
_SECTION = re.compile(r"^## ", re.MULTILINE)
_RUN_LINK = re.compile(r"\]\(((?:figures|tables)/[^)\s]+)\)")


def paper_slug(source: str) -> str:
    """The page name of a paper: its source file's stem (e.g. 'hasselgren2020-neural-temporal-...')."""
    return Path(source).stem


def paper_pages(run_dir: Path | None = None) -> dict[str, str | bytes]:
    """Site path -> content of one page per reproduced paper, generated from the published run ``run_dir``
    (default :data:`PAPERS_RUN`): the claims rows of that paper from ``tables/claims.md``, then the paper's
    section of ``REPORT.md`` (its tables and figures), with the run's status against the code at hand. Every
    figure or table the section links and the run holds is added beside the page (``papers/figures/...``), so
    the links resolve in the site."""
    from denoisers.report.published import RUN_FILE, run_status
    from denoisers.reproductions import all_reproductions
    from scenegen.config import load_config

    run_dir = Path(run_dir) if run_dir is not None else REPO_ROOT / PAPERS_RUN
    report = (run_dir / "REPORT.md").read_text()
    record = json.loads((run_dir / RUN_FILE).read_text())
    changes = run_status(load_config(REPO_ROOT / record["config"]), run_dir)
    status = ("Its settings and model keys equal the code's." if not changes else
              f"**It differs from the code at hand in {'; '.join(changes)}**: numbers below are the run's, not "
              "the code's.")
    claims_md = (run_dir / "tables" / "claims.md").read_text().splitlines()
    pages: dict[str, str | bytes] = {}
    for reproduction in all_reproductions():
        heading = f"## {reproduction.paper}: {reproduction.title}"
        start = report.find(heading + "\n")
        if start < 0:
            section = f"The run's REPORT.md has no section for {reproduction.paper}."
        else:
            body = report[start + len(heading):]
            end = _SECTION.search(body)
            section = body[:end.start() if end else len(body)].strip()
        ids = {claim.id for claim in reproduction.claims}
        rows = [line for line in claims_md[2:] if line.split("|")[1].strip() in ids]
        claims = "\n".join(claims_md[:2] + rows) if rows else "No claims of this paper in the run."
        for link in dict.fromkeys(_RUN_LINK.findall(section)):
            if (run_dir / link).is_file():
                pages[f"{PAPERS_DIR}/{link}"] = (run_dir / link).read_bytes()
        pages[f"{PAPERS_DIR}/{paper_slug(reproduction.source)}.md"] = "\n".join([
            f"# {reproduction.paper}", "", f"*{reproduction.title}*", "",
            f"Generated from the published run `{run_dir.name}` (`{record['config']}`, code `{record.get('run_commit')}`, "
            f"published {str(record.get('published', ''))[:10]}) when the manual is built; nothing here is typed. "
            f"{status} The rules behind each verdict: [Claims and verdicts](../claims.md#claims-and-verdicts).", "",
            "## Claims", "", claims, "", "## Tables and figures", "", section, ""])
    return pages


def training_progress_page(config_path: str = ISIK_CONFIG) -> str:
    """The page of every training of ``config_path`` (repository-relative) as the committed store holds it: stored,
    part-way or not started, wall time so far, the median logged seconds per step and an estimate of what is left
    (``python -m denoisers store progress --config <config> --markdown``)."""
    from denoisers.store import ModelStore
    from denoisers.store.progress import progress_table, training_progress
    from scenegen.config import load_config

    cfg = load_config(REPO_ROOT / config_path)
    store = ModelStore.of(cfg)
    if not store.root.is_absolute():
        store = ModelStore(REPO_ROOT / store.root)
    return "\n".join([
        f"# Training progress of `{config_path}`", "",
        "Generated from the committed [model store](model-store.md) when the manual is built; nothing here is typed. "
        "The run trains across machines that live about 3 hours ([Isik et al. 2021](isik2021.md)): each "
        "session continues the part-way checkpoints and publishes what finished. *wall so far* is the training "
        "jobs' wall time over every session (a trainer paused with `kill -STOP` keeps its clock); *s/step* is the "
        "median of the trainer's logged step rates (validation and pauses excluded); *left* is that rate times "
        "the steps left, borrowed from the run a half-budget twin shares or from a seed replica where a row has not "
        "trained. Rates depend on the host: bf16 on AVX-512 bf16 CPUs, fp32 elsewhere.", "",
        f"Same table: `python -m denoisers store progress --config {config_path} --markdown`.", "",
        progress_table(cfg, training_progress(cfg, store), markdown=True)])
