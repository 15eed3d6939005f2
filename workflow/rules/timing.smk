# The timing job (denoisers/jobs/timing.py): every configured row at every evaluated spp (and every size of a capacity
# ablation at evaluation.ablation_spp), timed on the same frames of
# one evaluated scene (evaluation.timing.scene) in interleaved rounds, and the renderer's samples/s on every
# evaluated scene at the same thread count. It takes every core, so no other job runs beside it; the report's speed numbers, the
# quality-versus-speed chart, the equal-time view and the speed claims read only this file.
#   time_methods: <out>/timing/timing.json
# The training-speed job (denoisers/training/speed.py): every learned model's training step (training.models, at
# its config size, on a synthetic batch: no inputs) per precision / layout variant, interleaved with sgemm; the
# report's "Training step speed" table reads it. Also every core, for the same reason.
#   time_training: <out>/timing/training.json

rule time_methods:
    input:
        scenes=timing_scene_dirs,
        noisy=timing_chunk_dirs,
        models=timing_model_dirs,
        tuning=timing_tuning_files,
    output:
        timing=results_path("timing/timing.json"),
    params:
        config_file=resolved_config_file,
        config_digest=timing_digest,
        scene=TIMING_SCENE,
        render_dir=results_path(f"renders/{TIMING_SCENE}"),
        results=results_root,
        scenes_root=results_path("scenes"),
        threads=timing_threads,
    log:
        results_path("logs/time_methods.log"),
    benchmark:
        results_path("benchmarks/time_methods.tsv")
    conda:
        "../envs/harness.yaml"
    # Every core of the machine (Snakemake caps it at --cores): the scheduler runs nothing else while the
    # methods are timed. The SLURM profile sets its threads explicitly.
    threads: os.cpu_count() or 1
    resources:
        mem_mb=8000,
        runtime=120,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers time --config {params.config_file} --scene {params.scene}"
        " --render-dir {params.render_dir} --scenes-root {params.scenes_root} --results {params.results}"
        " --out {output.timing} --threads {params.threads} > {log} 2>&1"


rule time_training:
    output:
        speed=results_path("timing/training.json"),
    params:
        config_file=resolved_config_file,
        config_digest=training_speed_digest,
        threads=training_speed_threads,
    log:
        results_path("logs/time_training.log"),
    benchmark:
        results_path("benchmarks/time_training.tsv")
    conda:
        "../envs/harness.yaml"
    # Every core (capped at --cores), like time_methods: nothing runs beside the timed steps. The torch threads
    # are training.speed.threads, else training.threads (the step as the training jobs run it), at most these.
    threads: os.cpu_count() or 1
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "python -m denoisers time-training --config {params.config_file} --out {output.speed}"
        " --threads {params.threads} > {log} 2>&1"
