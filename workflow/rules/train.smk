# Stage 3a: training of the learned denoisers on the train_* scenes (held-out validation scenes included).
#   train_denoiser: <output_dir>/models/{model}/ (best.pt, curves.csv/.png, validation.csv, summary.json, settings.json)
# {model} is an id of training.models, an ablation variant {ablation}_{variant}, a seed replica {id}_seed{k}
# (training.seeds) or a half-budget twin {id}_half (training.half_budget: the run of {id} stopped at half its
# steps; {id}'s job then continues that run). The trainer keeps
# a resumable checkpoint in <output_dir>/models/.work/ (not an output): a killed job continues from it.
# An ablation variant identical to its base model (same settings and budget) reuses the base's weights.
# A model in the model store (config store; denoisers.store) under its key is installed instead of trained: its
# training renders are then not inputs (model_source); store.force_training trains anyway. A stored part-way
# checkpoint of the run is continued.
#   verify_stored_model: <output_dir>/verify/{model}.json, a stored model retrained (store.verify) and compared.


rule train_denoiser:
    input:
        valid=check_model_target,
        same_as=same_training_dir,
        noisy=training_chunk_dirs("noisy"),
        reference=training_chunk_dirs("reference"),
    output:
        model_dir=directory(results_path("models/{model}")),
    params:
        config_file=resolved_config_file,
        config_digest=train_digest,
        store=model_store_source,
        render_root=render_root,
    log:
        results_path("logs/train/{model}.log"),
    benchmark:
        results_path("benchmarks/train/{model}.tsv")
    conda:
        "../envs/harness.yaml"
    # training.threads: the job trains on exactly these (part of the model's settings), even when Snakemake
    # scales the rule's threads down to --cores.
    threads: config["training"]["threads"]
    # After the renders, before the evaluation jobs: the long trainings keep both cores busy and the short
    # denoise/evaluate jobs fill a core whenever fewer than two trainings are ready.
    priority: 5
    resources:
        mem_mb=8000,
        runtime=lambda wildcards, attempt: training_runtime_minutes(config, wildcards.model) * attempt,  # budget
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers train --config {params.config_file} --model-id {wildcards.model}"
        " --render-root {params.render_root} --out {output.model_dir} > {log} 2>&1"


rule verify_stored_model:
    input:
        valid=check_verify_target,
        noisy=training_chunk_dirs("noisy", for_training=True),
        reference=training_chunk_dirs("reference", for_training=True),
    output:
        result=results_path("verify/{model}.json"),
    params:
        config_file=resolved_config_file,
        store=model_store_source,
        render_root=render_root,
    log:
        results_path("logs/verify/{model}.log"),
    benchmark:
        results_path("benchmarks/verify/{model}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["training"]["threads"]
    resources:
        mem_mb=8000,
        runtime=lambda wildcards, attempt: training_runtime_minutes(config, wildcards.model) * attempt,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers store verify --config {params.config_file} --model-id {wildcards.model}"
        " --render-root {params.render_root} --out {output.result} > {log} 2>&1"
