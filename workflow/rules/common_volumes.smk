# Helpers of workflow/rules/volumes.smk (input functions); included by the Snakefile after common.smk, whose
# imports and helpers they use.
# ---------------------------------------------------------------------------------------------
# The volumetric clips' evaluation (denoisers.jobs.volumes): every runnable row of volumes.rows denoises every
# vol_test_* clip at volumes.denoise_spp (rule denoise_volume_row, one job per row) and is scored against the
# volpath reference (evaluate_volume_row). Planned (importing torch) only when one of these jobs is part of the DAG.
# ---------------------------------------------------------------------------------------------
from denoisers.jobs.volumes import volume_test_scene_ids

# The evaluated clips: vol_test_* and the bring-your-own vol_custom_*.
VOLUME_TEST_SCENES = volume_test_scene_ids(config)
_volume_runs = []


def volume_run_list() -> list:
    """Every denoisers.evaluate.Run of the volume rows, runnable or not (denoisers.jobs.volumes.volume_runs)."""
    if VOLUME_TEST_SCENES and not _volume_runs:
        from denoisers.jobs.volumes import volume_runs

        _volume_runs.append(volume_runs(config))
    return _volume_runs[0] if _volume_runs else []


_volume_robustness_runs = []


def volume_robustness_run_list() -> list:
    """The volume rows' runs of the spike/NaN scenario (denoisers.jobs.volumes.volume_robustness_runs)."""
    if VOLUME_TEST_SCENES and not _volume_robustness_runs:
        from denoisers.jobs.volumes import volume_robustness_runs

        _volume_robustness_runs.append(volume_robustness_runs(config))
    return _volume_robustness_runs[0] if _volume_robustness_runs else []


def volume_rows(kind: str = "evaluation") -> list[str]:
    """The volume rows with a runnable run (kind 'robustness': of the spike scenario), in table order."""
    runs = volume_run_list() if kind == "evaluation" else volume_robustness_run_list()
    return list(dict.fromkeys(run.spec.id for run in runs if run.runnable))


def volume_robustness_dirs(wildcards=None) -> list[str]:
    return [results_path(f"volumes/robustness/{row}") for row in volume_rows("robustness")]


def volume_metrics_dirs(wildcards=None) -> list[str]:
    """Every row's metrics folder of the volume evaluation (stage target `volumes`, build_report)."""
    return [results_path(f"volumes/metrics/{row}") for row in volume_rows()]


def volume_denoised_dirs(wildcards=None) -> list[str]:
    return [results_path(f"volumes/denoised/{row}") for row in volume_rows()]


def check_volume_row_target(job_rule: str, pattern: str, kind: str = "evaluation"):
    """Input function of the volume row rules: a row that runs on the evaluated volumetric clips (kind
    'robustness': in their spike scenario)."""

    def check(wildcards) -> list:
        rows = volume_rows(kind)
        if wildcards.method not in rows:
            where = "in the volumetric clips' robustness scenario" if kind == "robustness" else \
                "run on the volumetric clips"
            raise impossible_target(job_rule, pattern, wildcards,
                                    f"row {wildcards.method} is not {where}; rows: {_listing(rows)} (evaluated "
                                    f"clips: {_listing(VOLUME_TEST_SCENES)})")
        return []

    return check
