# Stage 3b: parameters of hand-set baselines chosen on the training scenes only (grid search).
#   tune_method: results/tuning/{method}.json (every grid point's score, the chosen parameters)
# {method} is a registered method name with a tuning.methods entry. An evaluation row with
# params {tuned: true} depends on its method's file (input function method_tuning_file).


rule tune_method:
    input:
        noisy=training_chunk_dirs("noisy"),
        reference=training_chunk_dirs("reference"),
    output:
        result="results/tuning/{method}.json",
    params:
        config_file=resolved_config_file,
        config_digest=tuning_digest,
        render_dirs=training_render_dirs,
    log:
        "results/logs/tune/{method}.log",
    benchmark:
        "results/benchmarks/tune/{method}.tsv"
    conda:
        "../envs/harness.yaml"
    threads: config["tuning"]["threads"]
    resources:
        mem_mb=4000,
        runtime=60,
    wildcard_constraints:
        method="|".join(tuning_methods()) or "no_tuned_method",
    shell:
        "python -m denoisers tune --config {params.config_file} --method {wildcards.method}"
        " --render-dirs {params.render_dirs} --out {output.result} --threads {threads} > {log} 2>&1"
