# Param and input functions of the training and tuning rules (workflow/rules/train.smk, tune.smk): which
# models and tuning results exist, where each comes from (trained, the store, a same-training base), what
# renders they need. Included after common.smk, whose names it uses.


# ---------------------------------------------------------------------------------------------
# Training (workflow/rules/train.smk): one job per model of training.models and ablation variant.
# A model is retrained when its settings, the training data's config or the input files change.
# ---------------------------------------------------------------------------------------------
TRAIN_SCENES, VALIDATION_SCENES = training_split(config)


def model_dirs(wildcards=None) -> list[str]:
    """Every trained model directory (stage target `train`)."""
    return [model_dir(OUT, spec.id).as_posix() for spec in trained_model_specs(config)]


def training_chunk_dirs(kind: str, for_training: bool = False):
    """Input function: noisy or reference chunks of the training and validation scenes (of the job's model when it
    has one: a model with data.scenes volumes trains on the vol_train_* clips; tuning: the surface scenes)."""

    def chunk_dirs_of_training(wildcards) -> list[str]:
        scenes = TRAIN_SCENES + VALIDATION_SCENES
        if "method" in wildcards.keys() and tuning_stored(wildcards.method):
            return []  # tune_method installs the stored result
        if "model" in wildcards.keys():
            if not for_training and model_source(wildcards.model) != "train":
                return []  # installed from the store, or the weights of its same-training base
            scenes = sum(training_split(config, model_spec(config, wildcards.model)), [])
        return render_chunk_dirs(scenes, kind)

    return chunk_dirs_of_training


def model_source(model_id: str) -> str:
    """Where train_denoiser gets model ``model_id``: 'store' (installed; denoisers.store), 'same_training' (the
    weights of its base model) or 'train'."""
    if same_training_as(config, model_id):
        return "same_training"
    return "store" if stored_model(config, model_id) is not None else "train"


def model_store_source(wildcards) -> str:
    """Param of train_denoiser: the model's source and store key, so that a code change to the network or the step
    (a new key), or store.force_training, reruns the job."""
    return f"{model_source(wildcards.model)}:{model_key(config, wildcards.model)[:16]}"


def tuning_stored(method: str) -> bool:
    """Whether tune_method installs ``method``'s result from the store (denoisers.store.tuning)."""
    settings = config["store"]
    return settings["use"] and not settings["force_training"] and \
        tuning_entry(ModelStore.of(config), config, method) is not None


def needs_training_renders() -> bool:
    """Whether the DAG's default target needs the training scenes' renders: a model that trains, or a tuning that
    is not stored."""
    return any(not tuning_stored(method) for method in tuning_methods()) or \
        any(model_source(spec.id) == "train" for spec in trained_model_specs(config))


def default_scene_dirs() -> list[str]:
    """Scene directories of the default target: every scene, but the training scenes only when they are needed."""
    skip = set() if needs_training_renders() else set(TRAIN_SCENES + VALIDATION_SCENES)
    return [results_path(f"scenes/{scene}") for scene in SCENES if scene not in skip]


def default_chunk_dirs() -> list[str]:
    """Render chunks of the default target (as default_scene_dirs)."""
    skip = set() if needs_training_renders() else set(TRAIN_SCENES + VALIDATION_SCENES)
    return render_chunk_dirs([scene for scene in SCENES if scene not in skip])


def train_digest(wildcards) -> str:
    """Param: digest of the model's settings and of what its training data depend on (rerun trigger)."""
    return experiment.train_digest(config, wildcards.model)


def same_training_dir(wildcards) -> list[str]:
    """Input function of train_denoiser: the base model an ablation variant trains exactly as (its weights are
    reused, denoisers.training.models.same_training_as), or nothing."""
    source = same_training_as(config, wildcards.model)
    if source:
        return [model_dir(OUT, source).as_posix()]
    # A model whose half-budget twin trains here runs after it and continues its run (denoisers.training.job).
    half = f"{wildcards.model}{HALF_SUFFIX}"
    if half_of(config, half) and model_source(half) == "train" and model_source(wildcards.model) == "train":
        return [model_dir(OUT, half).as_posix()]
    return []


# ---------------------------------------------------------------------------------------------
# Tuning (workflow/rules/tune.smk): baseline parameters chosen on the training scenes only.
# ---------------------------------------------------------------------------------------------
def tuning_methods() -> list[str]:
    return [entry["method"] for entry in config.get("tuning", {}).get("methods", [])]


def training_render_dirs(wildcards=None) -> list[str]:
    return [results_path(f"renders/{scene}") for scene in TRAIN_SCENES + VALIDATION_SCENES]


def method_tuning_file(wildcards) -> list[str]:
    """Input function: the tuning result an evaluation row with params {tuned: true} reads, or nothing."""
    spec = method_spec(wildcards.method)
    return [results_path(f"tuning/{spec.method}.json")] if spec.params.get("tuned") else []


def tuning_store_source(wildcards) -> str:
    """Param of tune_method: 'store' or 'search', with the key (a code change or force_training reruns it)."""
    return f"{'store' if tuning_stored(wildcards.method) else 'search'}:{tuning_key(config, wildcards.method)[:16]}"


def tuning_digest(wildcards) -> str:
    return experiment.tuning_digest(config, wildcards.method)
