"""Published runs: the small outputs of a finished run committed under ``runs/<name>/``, and the README's result
numbers generated from them.

``publish_run`` copies a finished run's ``REPORT.md``, ``tables/*.csv`` / ``*.md`` (claims and targets included)
and the figures REPORT.md links (up to :data:`FIGURE_BUDGET_BYTES`; the rest are listed as left out; the copied
REPORT.md names every file it does not hold as plain text instead of linking it, :func:`unlink_left_out`) into the run folder,
with ``run.json``: the config file, the report's settings digest, every model's store key, the commit the run's
code came from and the date. Replacing an earlier published run, it writes ``CHANGES.md`` (the claims whose
verdict moved, :mod:`denoisers.report.verdict_changes`) and keeps the earlier run's tally in ``run.json``. ``run_status`` compares those digests with HEAD's, so a reader sees whether
the published numbers still describe the code at hand.

README blocks between ``<!-- published-run: <run folder> <config> -->`` and ``<!-- /published-run -->`` are
generated (:func:`readme_block`, ``python -m denoisers readme``); a test regenerates them and fails on any
difference, so no number there is typed by hand.
"""
from __future__ import annotations

import datetime
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

from denoisers.evaluate import BUDGET_ROLE, SEED_ROLE
from denoisers.report.verdict_changes import CHANGES_FILE, tally_text

RUN_FILE = "run.json"
#: Figures of one published run, in all (PNG/SVG that REPORT.md links).
FIGURE_BUDGET_BYTES = 6_000_000
BLOCK = re.compile(r"(<!-- published-run: (?P<run>\S+) (?P<config>\S+) -->\n)(?P<body>.*?)(<!-- /published-run -->)",
                   re.DOTALL)
_LINK = re.compile(r"\]\((figures/[^)\s]+)\)")
_CODE_LINE = re.compile(r"Code: `([0-9a-f]{7,40})`")


def unlink_left_out(text: str, published: set[str]) -> str:
    """REPORT.md text with every relative link (image or not) whose target is not in ``published`` (paths relative
    to the run folder) replaced by plain text naming the file in the run's results folder: a published copy has no
    broken link."""
    def replace(match: re.Match) -> str:
        target = match.group(3)
        if "://" in target or target.startswith("#") or target.split("#")[0] in published:
            return match.group(0)
        return f"{match.group(2) or target} (not published: `{target}` of the run's results)"

    return re.sub(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)", replace, text)


class PublishError(RuntimeError):
    """A run cannot be published; the message names what is missing."""


def _digests(cfg: dict) -> dict[str, Any]:
    from denoisers.experiment import report_digest
    from denoisers.store.keys import model_key
    from denoisers.training.models import trained_model_specs

    return {"report_digest": report_digest(cfg), "model_keys": {s.id: model_key(cfg, s.id) for s in trained_model_specs(cfg)}}


def publish_run(cfg: dict, config_file: str, results: Path, out: Path) -> dict[str, Any]:
    """Copy the finished run in ``results`` to ``out`` (replacing it); return run.json's record."""
    from denoisers.provenance import git_state

    results, out = Path(results), Path(out)
    report = results / "REPORT.md"
    if not report.is_file() or not (results / "tables" / "summary.csv").is_file():
        raise PublishError(f"{results}: no finished report (REPORT.md and tables/summary.csv); run the workflow first")
    text = report.read_text()
    figures, left_out, used = [], [], 0
    for name in dict.fromkeys(_LINK.findall(text)):
        path = results / name
        if not path.is_file():
            continue
        size = path.stat().st_size
        if used + size > FIGURE_BUDGET_BYTES:
            left_out.append(name)
            continue
        figures.append(name)
        used += size
    code = _CODE_LINE.search(text)
    record = {"config": config_file, "results": results.as_posix(), **_digests(cfg),
              "run_commit": code.group(1) if code else None, "published_at_commit": git_state(),
              "published": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "figures": figures, "figures_left_out": left_out, "figure_bytes": used}
    staging = out.with_name(f".{out.name}.staging")
    shutil.rmtree(staging, ignore_errors=True)
    (staging / "tables").mkdir(parents=True)
    for table in sorted((results / "tables").iterdir()):
        if table.suffix in (".csv", ".md"):
            shutil.copy2(table, staging / "tables" / table.name)
    previous = _previous_run(out, staging, record)
    if previous:
        record["previous"] = previous
    tables = [f"tables/{t.name}" for t in (staging / "tables").iterdir()]
    (staging / "REPORT.md").write_text(unlink_left_out(text, {*figures, *tables}))
    for name in figures:
        (staging / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(results / name, staging / name)
    (staging / RUN_FILE).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    shutil.rmtree(out, ignore_errors=True)
    staging.rename(out)
    return record


def _label(record: dict[str, Any]) -> str:
    return f"code {str(record.get('run_commit') or 'unknown')[:7]}, published {str(record.get('published', ''))[:10]}"


def _previous_run(out: Path, staging: Path, record: dict[str, Any]) -> dict[str, Any] | None:
    """When ``out`` holds an earlier published run with a claims table: write CHANGES.md into ``staging`` (the
    claims whose verdict moved) and return the earlier run's commit, date and tally for run.json."""
    import pandas as pd

    from denoisers.report.verdict_changes import changes_markdown, tally

    old_claims, new_claims = out / "tables" / "claims.csv", staging / "tables" / "claims.csv"
    if not (old_claims.is_file() and (out / RUN_FILE).is_file() and new_claims.is_file()):
        return None
    old_record = json.loads((out / RUN_FILE).read_text())
    old, new = pd.read_csv(old_claims), pd.read_csv(new_claims)
    (staging / CHANGES_FILE).write_text(changes_markdown(old, new, _label(old_record), _label(record)))
    return {"run_commit": old_record.get("run_commit"), "published": old_record.get("published"),
            "tally": tally(old)}


def run_status(cfg: dict, run_dir: Path) -> list[str]:
    """How the published run in ``run_dir`` differs from HEAD's settings and code (empty: it describes HEAD)."""
    record = json.loads((Path(run_dir) / RUN_FILE).read_text())
    now = _digests(cfg)
    changes = []
    if record.get("report_digest") != now["report_digest"]:
        changes.append("the config's settings digest")
    stale = sorted(m for m, key in now["model_keys"].items() if record.get("model_keys", {}).get(m) != key)
    if stale:
        changes.append(f"the keys (settings or code) of models {', '.join(stale)}")
    return changes


def _fmt(value: float, digits: int = 2) -> str:
    return "–" if value != value else f"{value:.{digits}f}"


#: summary.csv roles that the README table leaves to the report: seed replicas and half-budget twins.
HIDDEN_ROLES = (SEED_ROLE, BUDGET_ROLE)


def readme_block(repo: Path, run: str, config: str, link_prefix: str = "") -> str:
    """The generated body of a README block for published run folder ``run`` of config file ``config``; links are
    written as ``link_prefix + run`` (``../`` in docs/)."""
    import pandas as pd

    from scenegen.config import load_config

    run_dir = Path(repo) / run
    if not (run_dir / RUN_FILE).is_file():
        return (f"No run of `{config}` is published yet (`{run}/` is missing): no result number here is generated "
                f"from a run of this code.\n")
    record = json.loads((run_dir / RUN_FILE).read_text())
    summary = pd.read_csv(run_dir / "tables" / "summary.csv")
    claims = pd.read_csv(run_dir / "tables" / "claims.csv")
    changes = run_status(load_config(Path(repo) / config), run_dir)
    commit = record.get("run_commit") or "unknown"
    lines = [f"Published run [`{run}/`]({link_prefix}{run}/REPORT.md) of `{config}`, code `{commit[:12]}` "
             f"(published {record['published'][:10]}). "
             + ("Its settings and model keys equal HEAD's." if not changes else
                "**It differs from HEAD in " + "; ".join(changes) + "**: rerun and republish it."), ""]
    psnr = summary[summary["metric"] == "psnr"]
    # A model's seed replicas and half-budget twins are in the report; the row shows their seed mean and spread.
    hidden = psnr["role"].isin(HIDDEN_ROLES) if "role" in psnr else pd.Series(False, index=psnr.index)
    n_hidden = psnr.loc[hidden, "method_id"].nunique()
    psnr = psnr[~hidden]
    spps = sorted(psnr["spp"].unique())
    n = int(psnr["n_scenes"].max()) if len(psnr) else 0
    with_seeds = "n_seeds" in psnr and psnr["n_seeds"].fillna(1).max() > 1
    lines += [f"Mean PSNR (dB) over {n} evaluated scenes, with the 95 % interval"
              + (" (a trained row: the mean over its seeds; `seeds` gives their number and the standard deviation "
                 "of their PSNR at the row's first spp)" if with_seeds else "") + ":", "",
              "| method | " + " | ".join(f"{s} spp" for s in spps) + (" | seeds |" if with_seeds else " |"),
              "|---|" + "---|" * (len(spps) + with_seeds)]
    for method in dict.fromkeys(psnr["method_id"]):
        cells = []
        for spp in spps:
            row = psnr[(psnr["method_id"] == method) & (psnr["spp"] == spp)]
            cells.append("" if row.empty else f"{_fmt(row['mean'].iloc[0])} [{_fmt(row['ci_low'].iloc[0])}, "
                                               f"{_fmt(row['ci_high'].iloc[0])}]")
        if with_seeds:
            first = psnr[psnr["method_id"] == method].iloc[0]
            cells.append(f"{int(first['n_seeds'])} (sd {_fmt(first['seed_sd'])})" if first["n_seeds"] > 1 else "")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    if n_hidden:
        lines += ["", f"{n_hidden} seed replicas and half-budget twins are rows of the "
                      f"[report]({link_prefix}{run}/REPORT.md), not of this table."]
    counts = claims["verdict"].value_counts()
    lines += ["", "Claims: " + ", ".join(f"{int(count)} {verdict}" for verdict, count in counts.items())
              + f" (of {len(claims)}; [claims table]({link_prefix}{run}/tables/claims.md))."]
    previous = record.get("previous")
    if previous and (run_dir / CHANGES_FILE).is_file():
        lines[-1] += (f" The run it replaced ({_label(previous)}): {tally_text(previous['tally'])}; "
                      f"[what moved]({link_prefix}{run}/{CHANGES_FILE}).")
    lines += _cost_lines(run_dir, f"{link_prefix}{run}")
    lines.append("")
    return "\n".join(lines)


def _cost_lines(run_dir: Path, link: str) -> list[str]:
    """What the published run cost: its models' measured training time (tables/training.csv, each model's
    ``train_minutes``; a twin published from its full model's run, ``run_of``, counted with that run) and its
    jobs' time per stage (tables/job_times.csv, denoisers.report.job_times); empty where neither was published."""
    import pandas as pd

    from denoisers.report.job_times import PREPARATION_STAGES, hours_text, stage_seconds

    lines: list[str] = []
    training_file, jobs_file = run_dir / "tables" / "training.csv", run_dir / "tables" / "job_times.csv"
    training = pd.read_csv(training_file) if training_file.is_file() else None
    if training is not None and "run_of" in training:   # older runs cannot tell a shared twin's run apart
        trained = training[training["status"] == "trained"]
        trained = trained.assign(run_of=trained["run_of"].fillna("").astype(str))
        own = trained[trained["run_of"] == ""]
        lines += ["", f"Training: {len(trained)} models in {len(own)} runs, "
                      f"{hours_text(float(own['train_minutes'].sum()) * 60)} of training wall time as each run "
                      "measured it (validation included, and any pause of a stopped run; `s/step` is the median "
                      "logged step time; a half-budget twin published from its full model's run counts with that run; "
                      f"[training table]({link}/tables/training.md)), per model:", "",
                  "<details><summary>training time per model</summary>", "",
                  "| model | steps | training time | s/step | precision | CPU |", "|---|---|---|---|---|---|"]
        for row in trained.itertuples():
            time = "–" if row.train_minutes != row.train_minutes else hours_text(float(row.train_minutes) * 60)
            if row.run_of:
                time += f" (in {row.run_of}'s run)"
            steps = int(row.steps) if row.steps == row.steps else "–"
            lines.append(f"| {row.model} | {steps} | {time} | {_fmt(float(row.seconds_per_step), 3)} | "
                         f"{row.precision} | {row.cpu} |")
        lines += ["", "</details>"]
    if jobs_file.is_file():
        jobs = pd.read_csv(jobs_file)
        stages = stage_seconds(jobs)
        evaluation = {k: v for k, v in stages.items() if k not in PREPARATION_STAGES}
        lines += ["", f"Evaluation: {hours_text(sum(evaluation.values()))} of job time ("
                      + ", ".join(f"{k} {hours_text(v)}" for k, v in evaluation.items())
                      + "); the whole run's jobs: " + ", ".join(f"{k} {hours_text(v)}" for k, v in stages.items())
                      + f" (sums of job wall times; jobs ran side by side; [job times]({link}/tables/job_times.md))."]
    return lines


def update_blocks(path: Path, repo: Path, check: bool = False) -> list[str]:
    """Regenerate every published-run block of Markdown file ``path``; with ``check`` only report the blocks
    that differ (returns their run folders)."""
    text = Path(path).read_text()
    stale: list[str] = []

    prefix = os.path.relpath(Path(repo).resolve(), Path(path).resolve().parent)
    prefix = "" if prefix == "." else prefix.replace(os.sep, "/") + "/"

    def replace(match: re.Match) -> str:
        body = readme_block(repo, match["run"], match["config"], prefix)
        if body != match["body"]:
            stale.append(match["run"])
        return match.group(1) + body + match.group(5)

    new = BLOCK.sub(replace, text)
    if stale and not check:
        Path(path).write_text(new)
    return stale
