# Stage 3b: parameters of hand-set baselines chosen on the training scenes only (grid search).
#   tune_method: <output_dir>/tuning/{method}.json (every grid point's score, the chosen parameters)
# {method} is a registered method name with a tuning.methods entry. An evaluation row with
# params {tuned: true} depends on its method's file (input function method_tuning_file). A result in the model
# store (store/tuning; denoisers.store.tuning) under its key is installed instead: no training render is needed.


rule tune_method:
    input:
        valid=check_tuning_target,
        noisy=training_chunk_dirs("noisy"),
        reference=training_chunk_dirs("reference"),
    output:
        result=results_path("tuning/{method}.json"),
    params:
        config_file=resolved_config_file,
        config_digest=tuning_digest,
        store=tuning_store_source,
        render_dirs=training_render_dirs,
    log:
        results_path("logs/tune/{method}.log"),
    benchmark:
        results_path("benchmarks/tune/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["tuning"]["threads"]
    resources:
        mem_mb=4000,
        runtime=60,
    shell:
        "python -m denoisers tune --config {params.config_file} --method {wildcards.method}"
        " --render-dirs {params.render_dirs} --out {output.result} --threads {threads} > {log} 2>&1"
