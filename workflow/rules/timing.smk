# The timing job (denoisers/timing.py): every configured row at every evaluated spp (and every size of a capacity
# ablation at evaluation.ablation_spp), timed on the same frames of
# one evaluated scene (evaluation.timing.scene) in interleaved rounds, and the renderer's samples/s on every
# evaluated scene at the same thread count. It takes every core, so no other job runs beside it; the report's speed numbers, the
# quality-versus-speed chart, the equal-time view and the speed claims read only this file.
#   time_methods: <out>/timing/timing.json


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
    shell:
        "python -m denoisers time --config {params.config_file} --scene {params.scene}"
        " --render-dir {params.render_dir} --scenes-root {params.scenes_root} --results {params.results}"
        " --out {output.timing} --threads {params.threads} > {log} 2>&1"
