# Param and input functions of the evaluation rules (workflow/rules/evaluate.smk): the planned (row, scene, spp)
# runs, their output folders, inputs and digests. Included after common.smk, whose names it uses.


# ---------------------------------------------------------------------------------------------
# Evaluation (workflow/rules/evaluate.smk): which (method, evaluated scene, spp) jobs exist.
#
# The evaluated scenes are the test_* scenes and the external custom_* scenes (extra_scenes), each an
# independent unit of the report's comparisons; train_* scenes never are. The rows are evaluation.methods
# (each at its own `spp`, in the robustness scenario if its `robustness` is true) followed by one row
# per trained ablation variant (at its ablation's spp or evaluation.ablation_spp, not in robustness); see
# denoisers.evaluate.method_specs.
# A (row, spp) pair that needs more sample layers than were rendered (e.g. path tracing at 2 x 4 spp
# with 4 layers) is left out of the DAG; the report lists it as "not run" with the reason. Planning
# builds every planned method (importing torch), so it happens on first use, i.e. only when an
# evaluation target is part of the DAG.
# ---------------------------------------------------------------------------------------------
EVALUATED_SCENES = evaluated_scene_ids(config)
# Row id -> denoisers.evaluate.MethodSpec, resolved once (the ablation rows need the training models).
METHOD_SPECS = {spec.id: spec for spec in method_specs(config) + volume_method_specs(config)}


def method_spec(method_id: str):
    """The evaluation row (configured, ablation or volume row) of a job's {method} wildcard."""
    if method_id not in METHOD_SPECS:
        raise WorkflowError(f"no evaluation row with id {method_id!r}; rows: {', '.join(METHOD_SPECS)}")
    return METHOD_SPECS[method_id]


REPORT_OUTPUTS = report_outputs(config, root=OUT)
_planned_runs = {}


def planned_runs(kind: str = "evaluation") -> list:
    """Runnable denoisers.evaluate.Run objects of the evaluation ('evaluation') or the spike scenario ('robustness')."""
    if kind not in _planned_runs:
        from denoisers.evaluate import plan_runs, robustness_runs

        runs = plan_runs(config) if kind == "evaluation" else robustness_runs(config)
        _planned_runs[kind] = [run for run in runs if run.runnable]
    return _planned_runs[kind]


def planned_rows(kind: str = "evaluation") -> list[str]:
    """Row ids with at least one runnable (row, spp) of the evaluation or the spike scenario, in table order
    (none without evaluated scenes)."""
    return list(dict.fromkeys(run.spec.id for run in planned_runs(kind))) if EVALUATED_SCENES else []


def denoised_dirs(wildcards=None) -> list[str]:
    """Every row's denoised folder (stage target `denoise`): denoised/{row}/{scene}/spp{spp}/ inside."""
    return [results_path(f"denoised/{row}") for row in planned_rows()]


def metrics_dirs(wildcards=None) -> list[str]:
    """Every row's metrics folder: metrics/{row}/{scene}/spp{spp}.csv inside."""
    return [results_path(f"metrics/{row}") for row in planned_rows()]


def baseline_metrics_dirs(wildcards=None) -> list[str]:
    """Stage target `baselines`: the metrics of every row that uses no trained model (tuned rows read
    their tuning result, from the store when it is there), so no training job and, with stored tuning, no
    training render is planned."""
    return [results_path(f"metrics/{row}") for row in planned_rows()
            if method_model(method_spec(row).params) is None]


def robustness_dirs(wildcards=None) -> list[str]:
    """Every row's folder of the spike/NaN scenario: robustness/{row}/{scene}/spp{spp}/ inside."""
    return [results_path(f"robustness/{row}") for row in planned_rows("robustness")]


def evaluate_targets(wildcards=None) -> list[str]:
    """Stage target `evaluate`: metrics, the robustness scenario and the timing job."""
    return metrics_dirs() + robustness_dirs() + timing_outputs()


def check_row_target(job_rule: str, pattern: str, kind: str = "evaluation"):
    """Input function of the row rules: {method} is a row that runs at some spp (kind 'robustness': a row of
    the spike/NaN scenario)."""

    def check(wildcards) -> list:
        method = wildcards.method
        if method not in METHOD_SPECS:
            raise impossible_target(job_rule, pattern, wildcards, f"no evaluation row {method}; rows: "
                                    f"{_listing(METHOD_SPECS)}")
        if method not in planned_rows(kind):
            problem = (f"row {method} is not in the robustness scenario (robustness disabled, robustness: false, an "
                       "ablation row, or more sample layers needed than rendered)" if kind == "robustness" else
                       f"row {method} runs at no spp within the rendered sample layers")
            raise impossible_target(job_rule, pattern, wildcards, problem)
        return []

    return check


def method_model_dir(wildcards) -> list[str]:
    """Input function: the trained model an evaluation row uses (params.model), or nothing."""
    model = method_model(method_spec(wildcards.method).params)
    return [model_dir(OUT, model).as_posix()] if model else []


def scene_chunk_dirs(kind: str):
    """Input function: the noisy or reference chunk directories of the job's scene."""
    return lambda wildcards: render_chunk_dirs([wildcards.scene], kind)


def render_dir(wildcards) -> str:
    """Param: the scene's render directory (parent of its chunk directories)."""
    return results_path(f"renders/{wildcards.scene}")


def report_input(wildcards) -> dict[str, list[str]]:
    """Named inputs of build_report: every metrics CSV, denoised directory (timing, grid images),
    robustness output, the evaluated scenes' references (grids), the external scenes' manifests
    (their substitutions), the records of the timing and training-speed jobs, and the volume rows' metrics,
    denoised clips and references (the Iglesias-Guitian section)."""
    external = [results_path(f"scenes/{scene}") for scene in EVALUATED_SCENES if scene.startswith("custom_")]
    tuning = sorted({results_path(f"tuning/{run.spec.method}.json") for run in planned_runs()
                     if run.spec.params.get("tuned")})
    return {"metrics": metrics_dirs(), "denoised": denoised_dirs(), "robustness": robustness_dirs(),
            "reference": render_chunk_dirs(EVALUATED_SCENES, "reference"), "models": model_dirs(),
            "scenes": external, "tuning": tuning,
            "timing": timing_outputs(), "training_speed": training_speed_outputs(),
            "atlas": ATLAS_OUTPUTS["markdown"],
            "volumes": volume_metrics_dirs() + volume_denoised_dirs() + volume_robustness_dirs(),
            "volume_references": render_chunk_dirs(VOLUME_TEST_SCENES, "reference")}


def denoise_digest(wildcards) -> str:
    """Param: digest of what a denoised clip depends on besides its input files (rerun trigger)."""
    return experiment.denoise_digest(config, method_spec(wildcards.method))


def evaluate_digest(wildcards) -> str:
    return experiment.evaluate_digest(config)


def robustness_digest(wildcards) -> str:
    return experiment.robustness_digest(config, method_spec(wildcards.method))


def report_digest(wildcards) -> str:
    """The report states the whole configuration (split, render settings, evaluation)."""
    return experiment.report_digest(config)
