"""The files the report writes, listed while the Snakefile is parsed (no pandas, torch or matplotlib)."""
from __future__ import annotations

from denoisers.evaluate import evaluated_scene_ids
from denoisers.report.capacity import output_names as capacity_names
from denoisers.reproductions import all_reproductions
from denoisers.training.models import model_specs
from scenegen.catalog import CUSTOM_PREFIX

#: Cross-paper tables, written as tables/{name}.csv and tables/{name}.md.
CORE_TABLES: tuple[str, ...] = ("summary", "per_scene", "timing", "equal_time", "noise_floor", "robustness",
                                "claims", "targets", "runs", "split", "color_balance", "job_times")
#: Written when the config trains models: the training table and the training-speed job's table.
TRAINING_TABLES: tuple[str, ...] = ("training", "training_speed")
#: Written when external (custom_*) scenes are evaluated.
EXTERNAL_TABLES: tuple[str, ...] = ("external", "external_substitutions")
#: figures/{FIGURE_ROWS}: cross-paper chart file name -> the rows it draws (legend entries, grid columns).
FIGURE_ROWS = "rows.json"


def report_outputs(cfg: dict, root: str = "results") -> dict[str, list[str]]:
    """Files the report writes, grouped: 'tables' (CSV), 'tables_md', 'quality' (chart PNG + SVG), 'curves'
    (per-frame error per scene), 'grids', 'markdown', 'training_tables' / 'training_figures' (empty without
    training), 'figure_rows' (which rows each cross-paper chart draws), 'paper_tables' (CSV + Markdown) / 'paper_figures' of the reproduction modules and
    'capacity_tables' / 'capacity_figures' (one per capacity ablation, denoisers.report.capacity)."""
    scenes = evaluated_scene_ids(cfg)
    core = (CORE_TABLES + (EXTERNAL_TABLES if any(s.startswith(CUSTOM_PREFIX) for s in scenes) else ())
            + (("tuning",) if (cfg.get("tuning") or {}).get("methods") else ()))
    trained = bool(model_specs(cfg))
    paper_tables = [name for r in all_reproductions() for name in r.tables(cfg)]
    paper_figures = [name for r in all_reproductions() for name in r.figures(cfg)]
    return {"tables": [f"{root}/tables/{t}.csv" for t in core],
            "tables_md": [f"{root}/tables/{t}.md" for t in core],
            "quality": [f"{root}/figures/quality_vs_speed.png", f"{root}/figures/quality_vs_speed.svg"],
            "curves": [f"{root}/figures/frame_curves_{scene}.png" for scene in scenes],
            "grids": [f"{root}/figures/grid_{scene}_spp{spp}.png" for scene in scenes for spp in cfg["evaluation"]["spp"]]
            + [f"{root}/figures/robustness_grid.png"],
            "markdown": [f"{root}/REPORT.md"],
            "figure_rows": [f"{root}/figures/{FIGURE_ROWS}"],
            "training_tables": [f"{root}/tables/{t}.{ext}" for t in TRAINING_TABLES for ext in ("csv", "md")]
            if trained else [],
            "training_figures": [f"{root}/figures/training_curves.png"] if trained else [],
            "paper_tables": [f"{root}/tables/{t}.{ext}" for t in paper_tables for ext in ("csv", "md")],
            "paper_figures": [f"{root}/figures/{f}.png" for f in paper_figures],
            "capacity_tables": [f"{root}/tables/{t}.{ext}" for t in capacity_names(cfg) for ext in ("csv", "md")],
            "capacity_figures": [f"{root}/figures/{f}.png" for f in capacity_names(cfg)]}
