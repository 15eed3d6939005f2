# The volumetric clips' comparison (Iglesias-Guitian et al. 2022; config section `volumes`). Scenes vol_* are
# generated and rendered by generate_scene, render_noisy and render_reference (one chunk per clip, volumetric
# integrators); every runnable row of volumes.rows then runs on every vol_test_* clip at volumes.denoise_spp, one
# job per row for all its clips (denoisers.jobs.rows):
#   denoise_volume_row:    <output_dir>/volumes/denoised/{method}/{scene}/spp{spp}/ (as denoise_row's outputs)
#   evaluate_volume_row:   <output_dir>/volumes/metrics/{method}/{scene}/spp{spp}.csv + .json (per-frame metrics)
#   robustness_volume_row: <output_dir>/volumes/robustness/{method}/{scene}/spp{spp}/ (spikes and NaN/Inf
#                          injected; rows with robustness: true, at evaluation.robustness.spp)
# build_report reads them for the Iglesias-Guitian section (denoisers.reproductions.iglesias2022).


rule denoise_volume_row:
    input:
        valid=check_volume_row_target("denoise_volume_row", "volumes/denoised/{method}"),
        noisy=chunk_dirs_of(VOLUME_TEST_SCENES, "noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
    output:
        out_dir=directory(results_path("volumes/denoised/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=denoise_digest,
        render_root=results_path("renders"),
        results=results_root,
    log:
        results_path("logs/denoise_volume/{method}.log"),
    benchmark:
        results_path("benchmarks/denoise_volume/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=row_runtime(volume_run_list, VOLUME_TEST_SCENES),
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers denoise-row --kind volumes --config {params.config_file}"
        " --method-id {wildcards.method} --render-root {params.render_root} --results {params.results}"
        " --out {output.out_dir} --threads {threads} > {log} 2>&1"


rule evaluate_volume_row:
    input:
        valid=check_volume_row_target("evaluate_volume_row", "volumes/metrics/{method}"),
        denoised=results_path("volumes/denoised/{method}"),
        reference=chunk_dirs_of(VOLUME_TEST_SCENES, "reference"),
    output:
        out_dir=directory(results_path("volumes/metrics/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=evaluate_digest,
        render_root=results_path("renders"),
    log:
        results_path("logs/evaluate_volume/{method}.log"),
    benchmark:
        results_path("benchmarks/evaluate_volume/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=row_runtime(volume_run_list, VOLUME_TEST_SCENES),
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers evaluate-row --config {params.config_file}"
        " --denoised {input.denoised} --render-root {params.render_root} --out {output.out_dir} > {log} 2>&1"


rule robustness_volume_row:
    input:
        valid=check_volume_row_target("robustness_volume_row", "volumes/robustness/{method}", "robustness"),
        noisy=chunk_dirs_of(VOLUME_TEST_SCENES, "noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
        reference=chunk_dirs_of(VOLUME_TEST_SCENES, "reference"),
    output:
        out_dir=directory(results_path("volumes/robustness/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=robustness_digest,
        render_root=results_path("renders"),
        results=results_root,
    log:
        results_path("logs/robustness_volume/{method}.log"),
    benchmark:
        results_path("benchmarks/robustness_volume/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=row_runtime(volume_robustness_run_list, VOLUME_TEST_SCENES),
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers robustness-row --kind volume_robustness --config {params.config_file}"
        " --method-id {wildcards.method} --render-root {params.render_root} --results {params.results}"
        " --out {output.out_dir} --threads {threads} > {log} 2>&1"
