# Helpers of workflow/rules/volumes.smk (input functions); included by the Snakefile after common.smk, whose
# imports and helpers they use.
# ---------------------------------------------------------------------------------------------
# The volumetric clips' evaluation (denoisers.jobs.volumes): every runnable row of volumes.rows denoises every
# vol_test_* clip at volumes.denoise_spp (rule denoise_volume) and is scored against the volpath reference
# (evaluate_volume). Planned (importing torch) only when one of these jobs is part of the DAG.
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


def volume_robustness_dirs(wildcards=None) -> list[str]:
    return [results_path(f"volumes/robustness/{run.spec.id}/{scene}/spp{run.spp}")
            for run in volume_robustness_run_list() for scene in VOLUME_TEST_SCENES]


def volume_metrics_files(wildcards=None) -> list[str]:
    """Every metrics CSV of the volume evaluation (stage target `volumes`, build_report)."""
    return [results_path(f"volumes/metrics/{run.spec.id}/{scene}/spp{run.spp}.csv")
            for run in volume_run_list() if run.runnable for scene in VOLUME_TEST_SCENES]


def volume_denoised_dirs(wildcards=None) -> list[str]:
    return [results_path(f"volumes/denoised/{run.spec.id}/{scene}/spp{run.spp}")
            for run in volume_run_list() if run.runnable for scene in VOLUME_TEST_SCENES]


def check_volume_target(job_rule: str, pattern: str, kind: str = "evaluation"):
    """Input function of denoise_volume / evaluate_volume (robustness_volume: kind 'robustness'): an evaluated clip,
    and a row and spp that run on it."""
    from denoisers.jobs.volumes import volume_target_problem

    def check(wildcards) -> list:
        runs = volume_run_list() if kind == "evaluation" else volume_robustness_run_list()
        problem = volume_target_problem(VOLUME_TEST_SCENES, runs, wildcards.scene, wildcards.method,
                                        int(wildcards.spp))
        if problem:
            raise impossible_target(job_rule, pattern, wildcards, problem)
        return []

    return check
