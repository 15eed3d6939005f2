# Helpers of workflow/rules/stability.smk (input functions, digests); included by the Snakefile
# after common.smk, whose imports and helpers they use.
# ---------------------------------------------------------------------------------------------
# The stability suite's evaluation (workflow/rules/stability.smk, denoisers.jobs.stability): every configured
# row of evaluation.methods (not the ablation variants) denoises every stab_* clip at stability.denoise_spp
# (rule denoise_scenario), is scored against the reference, masks and events (score_scenario), and build_atlas
# writes the failure atlas. Planned (importing torch) only when one of these jobs is part of the DAG.
# ---------------------------------------------------------------------------------------------
ATLAS_OUTPUTS = atlas_outputs(config, root=OUT)
_stability_runs = []


def stability_run_list() -> list:
    """Runnable denoisers.evaluate.Run objects of the stability suite."""
    if STABILITY_SCENES and not _stability_runs:
        from denoisers.jobs.stability import stability_runs

        _stability_runs.append([run for run in stability_runs(config) if run.runnable])
    return _stability_runs[0] if _stability_runs else []


def scenario_outputs(kind: str):
    """Input function of build_atlas: every scores CSV ('scores') or denoised directory ('denoised') of the suite."""
    pattern = "stability/scores/{}/{}/spp{}.csv" if kind == "scores" else "stability/denoised/{}/{}/spp{}"
    return lambda wildcards: [results_path(pattern.format(run.spec.id, scene, run.spp))
                              for run in stability_run_list() for scene in STABILITY_SCENES]


def check_scenario_target(job_rule: str, pattern: str, controls: bool = False):
    """Input function of denoise_scenario (``controls``: the control clips too) / score_scenario: a stability
    scene, and a row and spp the suite runs."""
    from denoisers.jobs.stability import scenario_target_problem

    scenes = STABILITY_SCENES + (STABILITY_CONTROLS if controls else [])

    def check(wildcards) -> list:
        problem = scenario_target_problem(scenes, stability_run_list(), wildcards.scene, wildcards.method,
                                          int(wildcards.spp))
        if problem:
            raise impossible_target(job_rule, pattern, wildcards, problem)
        return []

    return check


def _scenario_control(scene: str) -> str | None:
    from scenegen.scenarios import scenario_control

    return scenario_control(config, scene)


def scenario_control_inputs(wildcards) -> list[str]:
    """Input function of score_scenario: the failure-free control clip's denoised output (same row and spp) and
    reference chunks, whose error is the lag metric's steady state; none for a scenario that is not animated."""
    control = _scenario_control(wildcards.scene)
    if control is None:
        return []
    return [results_path(f"stability/denoised/{wildcards.method}/{control}/spp{wildcards.spp}")] + [
        results_path(f"renders/{control}/reference/chunk_{chunk:03d}") for chunk in range(chunk_count(config, control))]


def scenario_control_args(wildcards) -> str:
    """Param of score_scenario: the control clip's --control-denoised / --control-render-dir ('' without one)."""
    control = _scenario_control(wildcards.scene)
    if control is None:
        return ""
    return (f"--control-denoised {results_path(f'stability/denoised/{wildcards.method}/{control}/spp{wildcards.spp}')}"
            f" --control-render-dir {results_path(f'renders/{control}')}")


def scenario_score_digest(wildcards) -> str:
    from denoisers.jobs.stability import score_digest

    return score_digest(config)


def stability_mask_dirs(wildcards=None) -> list[str]:
    return [results_path(f"stability/{scene}") for scene in STABILITY_SCENES]


def atlas_digest(wildcards) -> str:
    from denoisers.jobs.stability import atlas_digest as digest

    return digest(config)
