# Helpers of workflow/rules/stability.smk (input functions, digests); included by the Snakefile
# after common.smk, whose imports and helpers they use.
# ---------------------------------------------------------------------------------------------
# The stability suite's evaluation (workflow/rules/stability.smk, denoisers.jobs.stability): every configured
# row of evaluation.methods (not the ablation variants) denoises every stab_* clip at stability.denoise_spp
# (rule denoise_scenario_row, one job per row), is scored against the reference, masks and events
# (score_scenario_row), and build_atlas writes the failure atlas. Planned (importing torch) only when one of these jobs is part of the DAG.
# ---------------------------------------------------------------------------------------------
ATLAS_OUTPUTS = atlas_outputs(config, root=OUT)
_stability_runs = []


def stability_run_list() -> list:
    """Runnable denoisers.evaluate.Run objects of the stability suite."""
    if STABILITY_SCENES and not _stability_runs:
        from denoisers.jobs.stability import stability_runs

        _stability_runs.append([run for run in stability_runs(config) if run.runnable])
    return _stability_runs[0] if _stability_runs else []


def stability_run_rows() -> list[str]:
    """The rows with a runnable stability run, in table order."""
    return list(dict.fromkeys(run.spec.id for run in stability_run_list()))


def scenario_outputs(kind: str):
    """Input function of build_atlas: every row's scores folder ('scores') or denoised folder ('denoised')."""
    return lambda wildcards: [results_path(f"stability/{kind}/{row}") for row in stability_run_rows()]


def check_scenario_row_target(job_rule: str, pattern: str):
    """Input function of denoise_scenario_row / score_scenario_row: a row the suite runs."""

    def check(wildcards) -> list:
        rows = stability_run_rows()
        if wildcards.method not in rows:
            raise impossible_target(job_rule, pattern, wildcards,
                                    f"no runnable row {wildcards.method} of evaluation.methods on the stability "
                                    f"clips; rows: {_listing(rows)}")
        return []

    return check


def masks_root(wildcards) -> str:
    """Param of score_scenario_row: the folder of the scenarios' mask folders (stability/{scene}/)."""
    return results_path("stability")


def scenario_score_digest(wildcards) -> str:
    from denoisers.jobs.stability import score_digest

    return score_digest(config)


def stability_mask_dirs(wildcards=None) -> list[str]:
    return [results_path(f"stability/{scene}") for scene in STABILITY_SCENES]


def atlas_digest(wildcards) -> str:
    from denoisers.jobs.stability import atlas_digest as digest

    return digest(config)
