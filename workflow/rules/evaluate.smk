# Stage 3: denoising and evaluation of the test scenes and the external (custom_*) scenes, and the generated report.
# All paths are below the config's output_dir (<out>). A row with params {model: <id>} reads <out>/models/<id>/
# (rule train_denoiser) and depends on it.
#   denoise_clip:    <out>/denoised/{method}/{scene}/spp{spp}/frame_{t:04d}.exr + .png, timing.json
#   evaluate_clip:   <out>/metrics/{method}/{scene}/spp{spp}.csv (per-frame metrics) + .json (its settings digest)
#   robustness_clip: <out>/robustness/{method}/{scene}/spp{spp}/ (spikes and NaN/Inf injected)
#   build_report:    <out>/tables/, <out>/figures/, <out>/REPORT.md
# Each output records the digest of the settings it came from (denoisers.experiment); the report refuses
# to combine outputs whose digests disagree with its config.
# {method} is a row id: of evaluation.methods, or a trained ablation variant's model id (evaluated at
# evaluation.ablation_spp, not in the robustness scenario); the targets request the test_* and custom_* scenes
# (denoisers.evaluate.evaluated_scene_ids), never train_*; other targets are rejected when the DAG is built.


rule denoise_clip:
    input:
        valid=check_evaluation_target("denoise_clip", "denoised/{method}/{scene}/spp{spp}"),
        noisy=scene_chunk_dirs("noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
    output:
        out_dir=directory(results_path("denoised/{method}/{scene}/spp{spp}")),
    params:
        config_file=resolved_config_file,
        config_digest=denoise_digest,
        render_dir=render_dir,
        results=results_root,
    log:
        results_path("logs/denoise/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/denoise/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    # Timings are recorded in-process with this many torch threads; with 2 on a 2-core machine the
    # jobs run one at a time, so they do not disturb each other's timings.
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=60,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers denoise --config {params.config_file} --method-id {wildcards.method}"
        " --scene {wildcards.scene} --spp {wildcards.spp} --render-dir {params.render_dir}"
        " --results {params.results} --out {output.out_dir} --threads {threads} > {log} 2>&1"


rule evaluate_clip:
    input:
        valid=check_evaluation_target("evaluate_clip", "metrics/{method}/{scene}/spp{spp}.csv"),
        denoised=results_path("denoised/{method}/{scene}/spp{spp}"),
        reference=scene_chunk_dirs("reference"),
    output:
        csv=results_path("metrics/{method}/{scene}/spp{spp}.csv"),
        sidecar=results_path("metrics/{method}/{scene}/spp{spp}.json"),
    params:
        config_file=resolved_config_file,
        config_digest=evaluate_digest,
        render_dir=render_dir,
    log:
        results_path("logs/evaluate/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/evaluate/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers evaluate --config {params.config_file}"
        " --denoised {input.denoised} --render-dir {params.render_dir} --out {output.csv} > {log} 2>&1"


rule robustness_clip:
    input:
        valid=check_evaluation_target("robustness_clip", "robustness/{method}/{scene}/spp{spp}", "robustness"),
        noisy=scene_chunk_dirs("noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
        reference=scene_chunk_dirs("reference"),
    output:
        out_dir=directory(results_path("robustness/{method}/{scene}/spp{spp}")),
    params:
        config_file=resolved_config_file,
        config_digest=robustness_digest,
        render_dir=render_dir,
        results=results_root,
    log:
        results_path("logs/robustness/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/robustness/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=60,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers robustness --config {params.config_file} --method-id {wildcards.method}"
        " --scene {wildcards.scene} --spp {wildcards.spp} --render-dir {params.render_dir}"
        " --results {params.results} --out {output.out_dir} --threads {threads} > {log} 2>&1"


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
