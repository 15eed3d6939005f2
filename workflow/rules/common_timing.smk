# Helpers of workflow/rules/timing.smk (input functions, digests, threads); included by the Snakefile
# after common.smk, whose imports and helpers they use.
# ---------------------------------------------------------------------------------------------
# The timing job (workflow/rules/timing.smk): every configured row timed on one scene, alone.
# ---------------------------------------------------------------------------------------------
TIMING_SCENE = timing_scene(config) if timing_settings(config)["enabled"] else None
_timed_runs = []


def timed_run_list() -> list[tuple[str, int]]:
    """(row id, spp) of the timing job; planned (importing torch) only when a job needs it."""
    if TIMING_SCENE and not _timed_runs:
        _timed_runs.append(timed_runs(config))
    return _timed_runs[0] if _timed_runs else []


def timing_outputs(wildcards=None) -> list[str]:
    """The timing job's file, when the config times anything."""
    return [results_path("timing/timing.json")] if timed_run_list() else []


def timing_scene_dirs(wildcards=None) -> list[str]:
    """The evaluated scenes: the renderer's rate is measured on each."""
    return [results_path(f"scenes/{scene}") for scene in EVALUATED_SCENES]


def timing_chunk_dirs(wildcards=None) -> list[str]:
    return render_chunk_dirs([TIMING_SCENE], "noisy")


def timing_model_dirs(wildcards=None) -> list[str]:
    models = {method_model(METHOD_SPECS[row].params) for row, _ in timed_run_list()}
    return sorted(model_dir(OUT, model).as_posix() for model in models if model)


def timing_tuning_files(wildcards=None) -> list[str]:
    return sorted({results_path(f"tuning/{METHOD_SPECS[row].method}.json") for row, _ in timed_run_list()
                   if METHOD_SPECS[row].params.get("tuned")})


def timing_digest(wildcards) -> str:
    return experiment.Lineage(config).timing(TIMING_SCENE, [(METHOD_SPECS[row], spp) for row, spp in timed_run_list()])


def timing_threads(wildcards, threads) -> int:
    """Param: torch and Dr.Jit threads of the timing job (evaluation.timing.threads, else the job's threads)."""
    return timing_settings(config)["threads"] or threads


def training_speed_outputs(wildcards=None) -> list[str]:
    """The training-speed job's file (rule time_training), when a model of training.models is timed."""
    return [results_path(TRAINING_SPEED_FILE)] if speed_models(config) else []


def timing_targets(wildcards=None) -> list[str]:
    """Stage target `timing`: the timing job and the training-speed job."""
    return timing_outputs() + training_speed_outputs()


def training_speed_digest(wildcards) -> str:
    return experiment.training_speed_digest(config)


def training_speed_threads(wildcards, threads) -> int:
    """Param: torch threads of the training-speed job: training.speed.threads, else training.threads, at most the
    job's threads (the cores it gets), so the timed steps never oversubscribe them."""
    return min(speed_settings(config)["threads"], threads)
