# Shared set-up of the workflow: config validation, scene and chunk lists, input and param functions.
# Only functions and plain Python live here (no rules), so the rule files stay declarative.

import os
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from scenegen.config import (
    chunk_count,
    config_digest,
    config_problems,
    extra_scene,
    scene_frame_count,
    scene_ids,
)
# Light modules: torch and the methods are only imported when the evaluation runs are planned.
from denoisers.evaluate import evaluation_problems, method_specs, robustness_dir, evaluated_scene_ids
from denoisers.report import report_outputs
from denoisers.tuning import tuning_problems
from scenegen.overrides import coerce_override_strings
from denoisers.training.models import (method_model, model_dir, model_spec, model_specs, settings_digest,
                                       training_problems, training_split)


# ---------------------------------------------------------------------------------------------
# Validation. snakemake.utils.validate checks the schema and fills defaults in `config`; its
# message dumps whole schema fragments, so problems are re-described by scenegen.config, which
# names the key path and the allowed values, and also checks the cross-key constraints.
# ---------------------------------------------------------------------------------------------
# Nested command-line overrides (--config 'render={spp: 8}') arrive with string leaves: parse them.
coerce_override_strings(config, yaml.safe_load((Path(workflow.current_basedir) / "../schemas/config.schema.yaml").read_text()))
try:
    validate(config, "../schemas/config.schema.yaml")
    schema_error = None
except Exception as err:  # WorkflowError, or AttributeError when a section is not a mapping
    schema_error = err
config_errors = config_problems(config) or ([str(schema_error)] if schema_error else [])
if not config_errors:
    config_errors = evaluation_problems(config) + training_problems(config) + tuning_problems(config)
if config_errors:
    raise WorkflowError("invalid configuration:\n  - " + "\n  - ".join(config_errors))


wildcard_constraints:
    scene=r"(?:train|test)_\d{3}|custom_[a-z0-9_]+",
    chunk=r"\d{3}",
    method=r"[a-z0-9_]+",
    model=r"[a-z][a-z0-9_]*",
    spp=r"\d+",


SCENES = scene_ids(config)


def scene_dirs() -> list[str]:
    """Output directories of all scenes (stage target `scenes`)."""
    return [f"results/scenes/{scene}" for scene in SCENES]


def chunk_dirs(kind: str) -> list[str]:
    """Output directories of all render chunks of one kind ('noisy' or 'reference')."""
    return [
        f"results/renders/{scene}/{kind}/chunk_{chunk:03d}"
        for scene in SCENES
        for chunk in range(chunk_count(config, scene))
    ]


# ---------------------------------------------------------------------------------------------
# Passing the config to the CLI and rerunning jobs when it changes.
#
# The validated config (defaults filled, --config overrides applied) is dumped once per distinct
# config to a content-addressed file results/.config/<digest>.yaml at parse time; every job
# reads it with `--config`. Because the file name changes whenever any key changes, the path is
# handed over by a param function taking `output`: Snakemake treats such params as derived and
# leaves them out of the "params" rerun trigger. What does trigger reruns is a second param, the
# SHA-256 of only the config keys that job's output depends on; Snakemake records params in
# .snakemake/metadata and (default --rerun-triggers) reruns a job whose params changed. So e.g.
# raising n_train adds scenes without touching existing ones, and changing reference_spp reruns
# only the reference renders.
# ---------------------------------------------------------------------------------------------
RESOLVED_CONFIG_FILE = f"results/.config/{config_digest(config)[:16]}.yaml"


def write_resolved_config(path: str) -> None:
    """Write `config` to `path` once; atomic, so concurrent parses (e.g. cluster jobs) are safe."""
    target = Path(path)
    if target.exists():
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    partial.write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
    os.replace(partial, target)


write_resolved_config(RESOLVED_CONFIG_FILE)


def resolved_config_file(wildcards, output) -> str:
    """Param: the resolved config file (derived from `output`, hence not a rerun trigger)."""
    return RESOLVED_CONFIG_FILE


# Keys that do not change a scene's content or renders: they only say how many scenes exist or
# how frames are batched into jobs (frames_per_chunk is added back for the render jobs).
SCENE_LAYOUT_KEYS = {"n_train", "n_test", "frames_per_chunk"}
NOISY_ONLY_KEYS = {"spp", "extra_radiance_spp"}
REFERENCE_ONLY_KEYS = {"reference_spp", "reference_batch_spp"}
# Render keys that change both noisy and reference images (resolution, variant, path depth); the
# scene generator's preview render may use them too, so they are part of the scene digest.
RENDER_SHARED_KEYS = [
    f"render.{key}" for key in config["render"] if key not in NOISY_ONLY_KEYS | REFERENCE_ONLY_KEYS
]


def scene_settings(scene: str) -> dict:
    """The config values a scene's content depends on (not the number of scenes)."""
    if scene.startswith("custom_"):
        procedural = {"extra_scene": extra_scene(config, scene)}
    else:
        procedural = {key: value for key, value in config["scenes"].items() if key not in SCENE_LAYOUT_KEYS}
    return {"seed": config["seed"], "scenes": procedural, "render_shared": config_digest(config, *RENDER_SHARED_KEYS)}


def generate_scene_input(wildcards) -> dict[str, str]:
    """Named inputs of generate_scene: the XML file of a custom scene, nothing for procedural ones."""
    if wildcards.scene.startswith("custom_"):
        return {"xml": extra_scene(config, wildcards.scene)["xml"]}
    return {}


def generate_scene_digest(wildcards) -> str:
    """Param: digest of the config values that determine the scene (rerun trigger)."""
    return config_digest(scene_settings(wildcards.scene))


def render_digest(kind: str):
    """Param function: digest of the config values that determine a noisy/reference chunk."""
    own_keys = NOISY_ONLY_KEYS if kind == "noisy" else REFERENCE_ONLY_KEYS

    def digest(wildcards) -> str:
        settings = {
            "scene": scene_settings(wildcards.scene),
            "frames": scene_frame_count(config, wildcards.scene),
            "frames_per_chunk": config["scenes"]["frames_per_chunk"],
            "render": {key: config["render"][key] for key in sorted(own_keys)},
        }
        return config_digest(settings)

    return digest


# ---------------------------------------------------------------------------------------------
# Evaluation (workflow/rules/evaluate.smk): which (method, evaluated scene, spp) jobs exist.
#
# The evaluated scenes are the test_* scenes and the external custom_* scenes (extra_scenes), each an
# independent unit of the report's comparisons; train_* scenes never are. The rows are evaluation.methods
# (each at its own `spp`, in the robustness scenario if its `robustness` is true) followed by one row
# per trained ablation variant (at evaluation.ablation_spp, not in the robustness scenario); see
# denoisers.evaluate.method_specs.
# A (row, spp) pair that needs more sample layers than were rendered (e.g. path tracing at 2 x 4 spp
# with 4 layers) is left out of the DAG; the report lists it as "not run" with the reason. Planning
# builds every planned method (importing torch), so it happens on first use, i.e. only when an
# evaluation target is part of the DAG.
# ---------------------------------------------------------------------------------------------
EVALUATED_SCENES = evaluated_scene_ids(config)
# Row id -> denoisers.evaluate.MethodSpec, resolved once (the ablation rows need the training models).
METHOD_SPECS = {spec.id: spec for spec in method_specs(config)}


def method_spec(method_id: str):
    """The evaluation row (configured or ablation row) of a job's {method} wildcard."""
    if method_id not in METHOD_SPECS:
        raise WorkflowError(f"no evaluation row with id {method_id!r}; rows: {', '.join(METHOD_SPECS)}")
    return METHOD_SPECS[method_id]


REPORT_OUTPUTS = report_outputs(config)
_planned_runs = {}


def planned_runs(kind: str = "evaluation") -> list:
    """Runnable denoisers.evaluate.Run objects of the evaluation ('evaluation') or the spike scenario ('robustness')."""
    if kind not in _planned_runs:
        from denoisers.evaluate import plan_runs, robustness_runs

        runs = plan_runs(config) if kind == "evaluation" else robustness_runs(config)
        _planned_runs[kind] = [run for run in runs if run.runnable]
    return _planned_runs[kind]


def denoised_dirs(wildcards=None) -> list[str]:
    """Every denoised output directory (stage target `denoise`)."""
    return [
        f"results/denoised/{run.spec.id}/{scene}/spp{run.spp}" for run in planned_runs() for scene in EVALUATED_SCENES
    ]


def metrics_files(wildcards=None) -> list[str]:
    """Every per-frame metrics CSV."""
    return [f"results/metrics/{run.spec.id}/{scene}/spp{run.spp}.csv"
            for run in planned_runs() for scene in EVALUATED_SCENES]


def robustness_dirs(wildcards=None) -> list[str]:
    """Every output directory of the spike/NaN scenario."""
    return [
        str(robustness_dir("results", run.spec.id, scene, run.spp))
        for run in planned_runs("robustness")
        for scene in EVALUATED_SCENES
    ]


def evaluate_targets(wildcards=None) -> list[str]:
    """Stage target `evaluate`: metrics CSVs and the robustness scenario."""
    return metrics_files() + robustness_dirs()


# ---------------------------------------------------------------------------------------------
# Training (workflow/rules/train.smk): one job per model of training.models and ablation variant.
# A model is retrained when its settings, the training data's config or the input files change.
# ---------------------------------------------------------------------------------------------
TRAIN_SCENES, VALIDATION_SCENES = training_split(config)


def model_dirs(wildcards=None) -> list[str]:
    """Every trained model directory (stage target `train`)."""
    return [str(model_dir("results", spec.id)) for spec in model_specs(config)]


def training_chunk_dirs(kind: str):
    """Input function: noisy or reference chunks of the training and validation scenes."""

    def chunk_dirs_of_training(wildcards) -> list[str]:
        return [f"results/renders/{scene}/{kind}/chunk_{chunk:03d}" for scene in TRAIN_SCENES + VALIDATION_SCENES
                for chunk in range(chunk_count(config, scene))]

    return chunk_dirs_of_training


def train_digest(wildcards) -> str:
    """Param: digest of the model's settings and of what its training data depend on (rerun trigger)."""
    from denoisers.training.job import data_settings

    return settings_digest(model_spec(config, wildcards.model), data_settings(config))


def method_model_dir(wildcards) -> list[str]:
    """Input function: the trained model an evaluation row uses (params.model), or nothing."""
    model = method_model(method_spec(wildcards.method).params)
    return [str(model_dir("results", model))] if model else []


def scene_chunk_dirs(kind: str):
    """Input function: the noisy or reference chunk directories of the job's scene."""

    def chunk_dirs_of_scene(wildcards) -> list[str]:
        count = chunk_count(config, wildcards.scene)
        return [f"results/renders/{wildcards.scene}/{kind}/chunk_{chunk:03d}" for chunk in range(count)]

    return chunk_dirs_of_scene


def render_dir(wildcards) -> str:
    """Param: the scene's render directory (parent of its chunk directories)."""
    return f"results/renders/{wildcards.scene}"


def report_input(wildcards) -> dict[str, list[str]]:
    """Named inputs of build_report: every metrics CSV, denoised directory (timing, grid images),
    robustness output, the evaluated scenes' references (grids) and the external scenes' manifests
    (their substitutions)."""
    reference = [f"results/renders/{scene}/reference/chunk_{c:03d}" for scene in EVALUATED_SCENES
                 for c in range(chunk_count(config, scene))]
    external = [f"results/scenes/{scene}" for scene in EVALUATED_SCENES if scene.startswith("custom_")]
    tuning = sorted({f"results/tuning/{run.spec.method}.json" for run in planned_runs()
                     if run.spec.params.get("tuned")})
    return {"metrics": metrics_files(), "denoised": denoised_dirs(), "robustness": robustness_dirs(),
            "reference": reference, "models": model_dirs(), "scenes": external, "tuning": tuning}


def _method_settings(wildcards) -> dict:
    spec = method_spec(wildcards.method)
    return {"method": spec.method, "params": spec.params}


def denoise_digest(wildcards) -> str:
    """Param: digest of what a denoised clip depends on besides its input files (rerun trigger)."""
    settings = {key: config["evaluation"][key] for key in ("threads", "out_of_range_factor")}
    return config_digest({**_method_settings(wildcards), **settings})


def evaluate_digest(wildcards) -> str:
    return config_digest({"warmup_frames": config["evaluation"]["warmup_frames"]})


def robustness_digest(wildcards) -> str:
    settings = {key: config["evaluation"][key]
                for key in ("robustness", "warmup_frames", "threads", "out_of_range_factor")}
    return config_digest({**_method_settings(wildcards), **settings, "seed": config["seed"]})


def report_digest(wildcards) -> str:
    """The report states the whole configuration (split, render settings, evaluation)."""
    return config_digest(config)


# ---------------------------------------------------------------------------------------------
# Tuning (workflow/rules/tune.smk): baseline parameters chosen on the training scenes only.
# ---------------------------------------------------------------------------------------------
def tuning_methods() -> list[str]:
    return [entry["method"] for entry in config.get("tuning", {}).get("methods", [])]


def training_render_dirs(wildcards=None) -> list[str]:
    return [f"results/renders/{scene}" for scene in TRAIN_SCENES + VALIDATION_SCENES]


def method_tuning_file(wildcards) -> list[str]:
    """Input function: the tuning result an evaluation row with params {tuned: true} reads, or nothing."""
    spec = method_spec(wildcards.method)
    return [f"results/tuning/{spec.method}.json"] if spec.params.get("tuned") else []


def tuning_digest(wildcards) -> str:
    settings = {key: value for key, value in config["tuning"].items() if key != "methods"}
    entry = next(e for e in config["tuning"]["methods"] if e["method"] == wildcards.method)
    return config_digest({**settings, **entry})
