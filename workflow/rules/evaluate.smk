# Stage 3: denoising and evaluation of the test scenes and the external (custom_*) scenes, and the generated report.
# All paths are below the config's output_dir (<out>). A row with params {model: <id>} reads <out>/models/<id>/
# (rule train_denoiser) and depends on it.
#   denoise_row:     <out>/denoised/{method}/{scene}/spp{spp}/frame_{t:04d}.exr + .png, timing.json
#   evaluate_row:    <out>/metrics/{method}/{scene}/spp{spp}.csv (per-frame metrics) + .json (its settings digest)
#   robustness_row:  <out>/robustness/{method}/{scene}/spp{spp}/ (spikes and NaN/Inf injected)
#   build_report:    <out>/tables/, <out>/figures/, <out>/REPORT.md
# One job per row does every clip of the row (each evaluated scene at each of its spp, denoisers.jobs.rows): a
# clip is about a second of work and a process start (torch's import) costs two, so per-clip jobs spent most of
# the evaluation starting processes. The row's folder appears when all its clips are written.
# Each output records the digest of the settings it came from (denoisers.experiment); the report refuses
# to combine outputs whose digests disagree with its config.
# {method} is a row id: of evaluation.methods, or a trained ablation variant's model id (evaluated at
# evaluation.ablation_spp, not in the robustness scenario); the rows run on the test_* and custom_* scenes
# (denoisers.evaluate.evaluated_scene_ids), never on train_*.


rule denoise_row:
    input:
        valid=check_row_target("denoise_row", "denoised/{method}"),
        noisy=chunk_dirs_of(EVALUATED_SCENES, "noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
    output:
        out_dir=directory(results_path("denoised/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=denoise_digest,
        render_root=results_path("renders"),
        results=results_root,
    log:
        results_path("logs/denoise/{method}.log"),
    benchmark:
        results_path("benchmarks/denoise/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    # Timings are recorded in-process with this many torch threads; with 2 on a 2-core machine the
    # jobs run one at a time, so they do not disturb each other's timings.
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=row_runtime(planned_runs, EVALUATED_SCENES),
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers denoise-row --config {params.config_file} --method-id {wildcards.method}"
        " --render-root {params.render_root} --results {params.results} --out {output.out_dir}"
        " --threads {threads} > {log} 2>&1"


rule evaluate_row:
    input:
        valid=check_row_target("evaluate_row", "metrics/{method}"),
        denoised=results_path("denoised/{method}"),
        reference=chunk_dirs_of(EVALUATED_SCENES, "reference"),
    output:
        out_dir=directory(results_path("metrics/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=evaluate_digest,
        render_root=results_path("renders"),
    log:
        results_path("logs/evaluate/{method}.log"),
    benchmark:
        results_path("benchmarks/evaluate/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=row_runtime(planned_runs, EVALUATED_SCENES),
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers evaluate-row --config {params.config_file}"
        " --denoised {input.denoised} --render-root {params.render_root} --out {output.out_dir} > {log} 2>&1"


rule robustness_row:
    input:
        valid=check_row_target("robustness_row", "robustness/{method}", "robustness"),
        noisy=chunk_dirs_of(EVALUATED_SCENES, "noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
        reference=chunk_dirs_of(EVALUATED_SCENES, "reference"),
    output:
        out_dir=directory(results_path("robustness/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=robustness_digest,
        render_root=results_path("renders"),
        results=results_root,
    log:
        results_path("logs/robustness/{method}.log"),
    benchmark:
        results_path("benchmarks/robustness/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=row_runtime(lambda: planned_runs("robustness"), EVALUATED_SCENES),
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers robustness-row --config {params.config_file} --method-id {wildcards.method}"
        " --render-root {params.render_root} --results {params.results} --out {output.out_dir}"
        " --threads {threads} > {log} 2>&1"


rule build_report:
    input:
        unpack(report_input),
    output:
        tables=report(REPORT_OUTPUTS["tables"], caption="../report/tables.rst", category="Tables"),
        tables_md=REPORT_OUTPUTS["tables_md"],
        quality=report(REPORT_OUTPUTS["quality"], caption="../report/quality_vs_speed.rst", category="Figures"),
        curves=report(REPORT_OUTPUTS["curves"], caption="../report/frame_curves.rst", category="Figures"),
        grids=report(REPORT_OUTPUTS["grids"], caption="../report/grids.rst", category="Figures"),
        summary=report(REPORT_OUTPUTS["markdown"], caption="../report/summary.rst", category="Summary"),
        figure_rows=REPORT_OUTPUTS["figure_rows"],
        training=report(REPORT_OUTPUTS["training_tables"] + REPORT_OUTPUTS["training_figures"],
                        caption="../report/training.rst", category="Training"),
        papers=report(REPORT_OUTPUTS["paper_tables"] + REPORT_OUTPUTS["paper_figures"],
                      caption="../report/papers.rst", category="Papers"),
        capacity=report(REPORT_OUTPUTS["capacity_tables"] + REPORT_OUTPUTS["capacity_figures"],
                        caption="../report/capacity.rst", category="Training"),
    params:
        config_file=resolved_config_file,
        config_digest=report_digest,
        results=results_root,
    log:
        results_path("logs/build_report.log"),
    benchmark:
        results_path("benchmarks/build_report.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers report --config {params.config_file}"
        " --results {params.results} > {log} 2>&1"
