# Monte Carlo denoising reference harness: seeded procedural scenes -> Mitsuba 3 noisy per-sample
# renders and high-spp references (OpenEXR) -> learned denoisers trained on the training scenes ->
# denoised test clips, per-frame metrics and a generated report. Rules live in workflow/rules/, the
# config schema in workflow/schemas/config.schema.yaml. Stage targets: `snakemake scenes`, `snakemake renders`,
# `snakemake train`, `snakemake denoise`, `snakemake evaluate`, `snakemake baselines` (the rows without a trained
# model), `snakemake timing`, `snakemake report`,
# `snakemake stability` (the temporal-stability scenario clips, their masks and the failure atlas), `snakemake volumes`
# (the volumetric clips: scenes, renders, the volume rows denoised and scored), `snakemake verify` (stored models
# retrained and compared, config store.verify).
# Every output goes below the config's output_dir (default results/; config/smoke.yaml: results/smoke/);
# `python -m denoisers clean --config <file>` removes one experiment's outputs.

from snakemake.utils import min_version

min_version("9.0")


# The default config only when no --configfile is given: Snakemake merges a workflow's configfile under every
# command-line one, so keys that config/config.yaml sets and another config leaves out (e.g.
# render.test_reference_spp_per_scene, which names the default run's test scenes) leaked into smoke, isik2021 and
# cluster runs, while `load_config(<file>)` (the Python side) saw the file alone. Every shipped config is complete.
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/common_training.smk"
include: "workflow/rules/common_evaluate.smk"
include: "workflow/rules/common_timing.smk"
include: "workflow/rules/common_stability.smk"
include: "workflow/rules/common_volumes.smk"
include: "workflow/rules/scenes.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/tune.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/timing.smk"
include: "workflow/rules/stability.smk"
include: "workflow/rules/volumes.smk"


localrules:
    all,
    scenes,
    renders,
    train,
    denoise,
    evaluate,
    baselines,
    timing,
    report,
    stability,
    volumes,
    verify,


rule scenes:
    input:
        scene_dirs(),


rule renders:
    input:
        render_chunk_dirs(SCENES),


rule train:
    input:
        model_dirs(),


# The evaluation targets take input functions: the (method, spp) pairs are planned (importing
# torch and every method) only when one of these targets is part of the DAG.
rule denoise:
    input:
        denoised_dirs,


rule evaluate:
    input:
        evaluate_targets,


# The rows that need no training (noisy input, path tracing, EAW, SVGF, RLS, wRLS, OIDN, a user's own filter):
# denoised and scored on the evaluated scenes, with no training job in the DAG.
rule baselines:
    input:
        baseline_metrics_dirs,


rule timing:
    input:
        timing_targets,


rule report:
    input:
        rules.build_report.output,


# The stability scenarios (stab_* scenes): scenes, renders, masks, every configured row denoised and scored on
# them, and the failure atlas (<out>/stability/ATLAS.md; build_report links it).
rule stability:
    input:
        stability_outputs(),


# The volumetric clips (vol_* scenes, config section volumes): scenes, renders, every volume row denoised and scored
# on the vol_test_* clips (the report's Iglesias-Guitian section reads them).
rule volumes:
    input:
        volume_outputs(),
        volume_metrics_dirs,
        volume_robustness_dirs,


# Retrain the models of store.verify.models and compare them with the stored runs (<out>/verify/{model}.json).
rule verify:
    input:
        verify_outputs,     # an input function: finding the stored models keys every model, only when asked


# Everything implemented so far; the default target. The training scenes (and volumetric training clips) are
# rendered only when something needs them: a model that is not installed from the store, or tuning.
rule all:
    default_target: True
    input:
        default_scene_dirs(),
        default_chunk_dirs(),
        rules.train.input,
        rules.build_report.output,
        rules.stability.input,
        default_volume_outputs(),
        volume_metrics_dirs,
        volume_robustness_dirs,
