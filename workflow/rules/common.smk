# Shared set-up of the workflow: config validation, the experiment folder, scene and chunk lists, the resolved
# config and the params of the scene and render jobs. Only functions and plain Python live here (no rules), so the
# rule files stay declarative; the other stages' functions are in common_<stage>.smk, included after this file.

import os
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from scenegen.catalog import chunk_count, extra_scene, scene_ids, stability_scene_ids, volume_extra, volume_scene_ids
from scenegen.config import config_digest, config_problems, output_root
from scenegen.custom.check import custom_scene_problems
from scenegen.digests import masks_digest as scene_masks_digest
from scenegen.scenarios import stability_control_ids
# Light modules: torch and the methods are only imported when the evaluation runs are planned.
from denoisers import experiment
from denoisers.device import DeviceError, resolve_config_device
from denoisers.evaluate import (evaluation_problems, method_specs, robustness_dir, evaluated_scene_ids,
                                volume_method_specs)
from denoisers.jobs.volumes import volume_problems
from denoisers.report import report_outputs
from denoisers.report.atlas import atlas_outputs
from denoisers.jobs.timing import timed_runs, timing_scene, timing_settings
from denoisers.training.speed import TRAINING_SPEED_FILE, speed_models, speed_settings
from denoisers.jobs.tuning import tuning_problems
from scenegen.overrides import coerce_override_strings
from scenegen.retry_gate import clear_markers as clear_retry_markers
from denoisers.training.models import (HALF_SUFFIX, half_of, method_model, model_dir, model_spec, same_training_as,
                                       trained_model_specs, training_problems, training_runtime_minutes,
                                       training_split)
from denoisers.store import ModelStore, model_key
from denoisers.store.tuning import tuning_entry, tuning_key
from denoisers.store.workflow import stored_model, verify_models, verify_problems


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
if schema_error is None:
    # The later checks read a schema-valid config. Every group runs, so all problems come in one message; a group
    # that cannot run beside the problems already found is named instead. custom_scene_problems parses every
    # custom scene (not rendered): bad XML, unknown plugins, missing files.
    for check in (evaluation_problems, training_problems, tuning_problems, volume_problems, verify_problems,
                  custom_scene_problems):
        try:
            config_errors += check(config)
        except Exception as err:
            if not config_errors:
                raise
            config_errors.append(f"({check.__name__} could not run beside the problems above: {err})")
if config_errors:
    raise WorkflowError("invalid configuration:\n  - " + "\n  - ".join(config_errors))
# compute.device auto becomes cpu or cuda here, once, and render.variant the variant it runs as there: every digest,
# store key and job reads the resolved value (denoisers.device; on a cluster set cuda, the login node may have none).
try:
    resolve_config_device(config)
except (DeviceError, ValueError) as err:
    raise WorkflowError(f"invalid configuration: {err}") from None


wildcard_constraints:
    scene=r"(?:train|test)_\d{3}|custom_[a-z0-9_]+|stab_[a-z0-9_]+|vol_(?:test|train)_[a-z_]+_\d{3}|vol_custom_[a-z0-9_]+",
    chunk=r"\d{3}",
    method=r"[a-z0-9_]+",
    model=r"[a-z][a-z0-9_]*",
    spp=r"\d+",


SCENES = scene_ids(config)
# The stability scenarios' scenes (stab_{name}; target `stability`): generated and rendered by the same rules,
# never trained on or evaluated (not in SCENES, which the split and the evaluation read).
STABILITY_SCENES = stability_scene_ids(config)
# Their failure-free controls (stab_{name}__still: each animated scenario held at its final frame), rendered and
# denoised like the scenarios; they give the steady state of the lag metric (no masks, no scores of their own).
STABILITY_CONTROLS = stability_control_ids(config)
# The volumetric clips (vol_{split}_{scenario}_{index}; target `volumes`): generated and rendered by the same rules
# with the volumetric integrators; not in SCENES (the surface scenes' split, training and evaluation).
VOLUME_SCENES = volume_scene_ids(config)
# The experiment's folder (config key output_dir): every output, log and benchmark of every rule is below it,
# so two configs with different output_dir never share a file.
OUT = output_root(config).as_posix()


#: Environment variable naming the SLURM partition of the jobs that compute on the GPU under compute.device cuda.
GPU_PARTITION_VARIABLE = "MCDN_SLURM_GPU_PARTITION"


def gpu_resources() -> dict:
    """Resources of the jobs that compute on compute.device (Mitsuba, torch). Under cuda one GPU (the SLURM
    executor's `gpu`, i.e. --gpus=1) and, when $MCDN_SLURM_GPU_PARTITION is set, that partition; none on the CPU."""
    if config["compute"]["device"] != "cuda":
        return {}
    partition = os.environ.get(GPU_PARTITION_VARIABLE)
    return {"gpu": 1, **({"slurm_partition": partition} if partition else {})}


def results_path(path: str) -> str:
    """``path`` (may hold {wildcards}) inside the experiment folder: <output_dir>/<path>."""
    return f"{OUT}/{path}"


def results_root(wildcards, output) -> str:
    """Param: the experiment folder, handed to the CLIs (derived from `output`: not a rerun trigger)."""
    return OUT


def render_root(wildcards, output) -> str:
    """Param: the folder of every scene's renders (the training job reads the training scenes below it)."""
    return results_path("renders")


def scene_dirs() -> list[str]:
    """Output directories of all scenes (stage target `scenes`)."""
    return [results_path(f"scenes/{scene}") for scene in SCENES]


def render_chunk_dirs(scenes: list[str], kinds: str | tuple[str, ...] = ("noisy", "reference")) -> list[str]:
    """Every render chunk folder of ``scenes`` (renders/{scene}/{kind}/chunk_NNN), kind by kind; ``kinds``: one
    kind ('noisy' or 'reference') or several."""
    kinds = (kinds,) if isinstance(kinds, str) else kinds
    return [results_path(f"renders/{scene}/{kind}/chunk_{chunk:03d}") for kind in kinds for scene in scenes
            for chunk in range(chunk_count(config, scene))]


def chunk_dirs_of(scenes: list[str], kind: str):
    """Input function: the ``kind`` render chunks of a fixed list of scenes (e.g. every evaluated scene)."""
    return lambda wildcards: render_chunk_dirs(scenes, kind)


def row_runtime(run_list, scenes: list[str]):
    """Resource function of a row job: its wall-time limit (SLURM) in minutes, 10 plus one per clip (the row's
    runnable runs in ``run_list()`` times ``scenes``), grown with the attempt."""

    def runtime(wildcards, attempt: int) -> int:
        spps = sum(1 for run in run_list() if run.spec.id == wildcards.method and run.runnable)
        return (10 + max(spps, 1) * len(scenes)) * attempt

    return runtime


# ---------------------------------------------------------------------------------------------
# Targets that cannot exist for this config (a training scene's denoised clip, a chunk out of range, a
# scene, row, model or spp the config does not have) are rejected while the DAG is built: the first
# input function of every job rule checks its wildcards and raises a WorkflowError naming the target
# and what is allowed (the wildcard constraints above only check the shape of ids).
# ---------------------------------------------------------------------------------------------
def impossible_target(job_rule: str, pattern: str, wildcards, problem: str) -> WorkflowError:
    target = results_path(pattern).format(**dict(wildcards.items()))
    # Split before the colon: the linter reads a line holding the word rule followed by a colon as a rule.
    return WorkflowError(f"impossible target {target} (rule {job_rule}) for this config (output_dir {OUT})"
                         f": {problem}")


def _listing(values) -> str:
    return ", ".join(map(str, values)) or "none"


def check_scene_target(wildcards, job_rule: str = "generate_scene", pattern: str = "scenes/{scene}") -> list:
    known = SCENES + STABILITY_SCENES + STABILITY_CONTROLS + VOLUME_SCENES
    if wildcards.scene not in known:
        raise impossible_target(job_rule, pattern, wildcards, f"scene {wildcards.scene} is not in this config; "
                                f"scenes: {_listing(known)}")
    return []


def check_stability_target(wildcards) -> list:
    """Input function of derive_masks: a stability scene of this config (stability.enabled, stability.scenarios)."""
    if wildcards.scene not in STABILITY_SCENES:
        raise impossible_target("derive_masks", "stability/{scene}", wildcards,
                                f"scene {wildcards.scene} is not a stability scenario of this config "
                                f"(stability.enabled, stability.scenarios); stability scenes: "
                                f"{_listing(STABILITY_SCENES)}")
    return []


def stability_outputs(wildcards=None) -> list[str]:
    """Stage target `stability`: every scenario's scene, renders and masks (the masks need the rest), and the
    failure atlas (build_atlas; every configured row denoised and scored on every scenario)."""
    return [results_path(f"stability/{scene}") for scene in STABILITY_SCENES] + ATLAS_OUTPUTS["all"]


def volume_outputs(wildcards=None) -> list[str]:
    """Stage target `volumes`: every volumetric clip's noisy and reference renders (one chunk each)."""
    return render_chunk_dirs(VOLUME_SCENES)


def default_volume_outputs(wildcards=None) -> list[str]:
    """The volumetric renders of the default target: the vol_train_* clips only when a model trains on them."""
    training = {scene for spec in trained_model_specs(config) if model_source(spec.id) == "train"
                for scene in sum(training_split(config, spec), [])}
    scenes = [scene for scene in VOLUME_SCENES if not scene.startswith("vol_train_") or scene in training]
    return render_chunk_dirs(scenes)


def masks_digest(wildcards) -> str:
    """Param: digest of the settings a scenario's masks depend on (its renders'; rerun trigger)."""
    return scene_masks_digest(config, wildcards.scene)


def check_chunk_target(kind: str):
    """Input function of render_{kind}: the scene exists and has the chunk."""
    job_rule, pattern = f"render_{kind}", f"renders/{{scene}}/{kind}/chunk_{{chunk}}"

    def check(wildcards) -> list:
        check_scene_target(wildcards, job_rule, pattern)
        count = chunk_count(config, wildcards.scene)
        if int(wildcards.chunk) >= count:
            raise impossible_target(job_rule, pattern, wildcards, f"scene {wildcards.scene} has {count} chunk(s) of "
                                    f"scenes.frames_per_chunk = {config['scenes']['frames_per_chunk']} frames: "
                                    f"chunk_000..chunk_{count - 1:03d}")
        return []

    return check


def check_model_target(wildcards) -> list:
    ids = [spec.id for spec in trained_model_specs(config)]
    if wildcards.model not in ids:
        raise impossible_target("train_denoiser", "models/{model}", wildcards,
                                f"no model {wildcards.model} in training.models or training.ablations; "
                                f"models: {_listing(ids)}")
    return []


def check_verify_target(wildcards) -> list:
    """verify_stored_model: the model must be listed in store.verify.models and stored under this config's key."""
    if wildcards.model not in verify_models(config):
        raise impossible_target("verify_stored_model", "verify/{model}.json", wildcards,
                                f"model {wildcards.model!r} is not in store.verify.models "
                                f"({_listing(verify_models(config))})")
    if ModelStore.of(config).model_entry(config, wildcards.model) is None:
        raise impossible_target("verify_stored_model", "verify/{model}.json", wildcards,
                                f"model {wildcards.model!r} is not in the store {config['store']['path']} under this "
                                "config's key")
    return []


def verify_outputs(wildcards=None) -> list[str]:
    """Target `verify`: every model of store.verify.models retrained and compared with its stored run."""
    return [results_path(f"verify/{model}.json") for model in verify_models(config)]


def check_tuning_target(wildcards) -> list:
    if wildcards.method not in tuning_methods():
        raise impossible_target("tune_method", "tuning/{method}.json", wildcards,
                                f"method {wildcards.method} has no tuning.methods entry; tuned methods: "
                                f"{_listing(tuning_methods())}")
    return []


# ---------------------------------------------------------------------------------------------
# Passing the config to the CLI and rerunning jobs when it changes.
#
# The validated config (defaults filled, --config overrides applied) is dumped once per distinct
# config to a content-addressed file <output_dir>/.config/<digest>.yaml before the first job; every job
# reads it with `--config`. Because the file name changes whenever any key changes, the path is
# handed over by a param function taking `output`: Snakemake treats such params as derived and
# leaves them out of the "params" rerun trigger. What does trigger reruns is a second param, the
# SHA-256 of only the config keys that job's output depends on; Snakemake records params in
# .snakemake/metadata and (default --rerun-triggers) reruns a job whose params changed. So e.g.
# raising n_train adds scenes without touching existing ones, and changing reference_spp reruns
# only the reference renders (train_reference_spp: only the train_* scenes' ones). The digests are
# computed by denoisers.experiment, which also combines them into the lineage digests that outputs
# record and the report checks.
# ---------------------------------------------------------------------------------------------
RESOLVED_CONFIG_FILE = results_path(f".config/{config_digest(config)[:16]}.yaml")


def write_resolved_config(path: str) -> None:
    """Write `config` to `path` once; atomic, so concurrent parses (e.g. cluster jobs) are safe."""
    target = Path(path)
    if target.exists():
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    partial.write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
    os.replace(partial, target)



# Written when jobs are about to run, not at parse time: a dry run (-n) and a failed config check write nothing.
# A new run also forgets which jobs failed deterministically in the last one (scenegen.retry_gate: their retries
# within one run are refused; the next run, after a fix, tries them again). onstart runs in the main process only.
onstart:
    write_resolved_config(RESOLVED_CONFIG_FILE)
    clear_retry_markers(Path(OUT) / "logs")


def resolved_config_file(wildcards, output) -> str:
    """Param: the resolved config file (derived from `output`, hence not a rerun trigger)."""
    return RESOLVED_CONFIG_FILE


def generate_scene_input(wildcards) -> dict[str, str]:
    """Named inputs of generate_scene: the XML file of a custom scene, the .npy field of a bring-your-own volume,
    nothing for procedural ones."""
    check_scene_target(wildcards)
    if wildcards.scene.startswith("custom_"):
        return {"xml": extra_scene(config, wildcards.scene)["xml"]}
    if wildcards.scene.startswith("vol_custom_"):
        return {"npy": volume_extra(config, wildcards.scene)["npy"]}
    return {}


def generate_scene_digest(wildcards) -> str:
    """Param: digest of the config values that determine the scene (rerun trigger)."""
    return experiment.scene_digest(config, wildcards.scene)


def render_digest(kind: str):
    """Param function: digest of the config values that determine a noisy/reference chunk."""

    def digest(wildcards) -> str:
        return experiment.render_digest(config, wildcards.scene, kind)

    return digest
