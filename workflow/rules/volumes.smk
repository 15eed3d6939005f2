# The volumetric clips' comparison (Iglesias-Guitian et al. 2022; config section `volumes`). Scenes vol_* are
# generated and rendered by generate_scene, render_noisy and render_reference (one chunk per clip, volumetric
# integrators); every runnable row of volumes.rows then runs on every vol_test_* clip at volumes.denoise_spp:
#   denoise_volume:  <output_dir>/volumes/denoised/{method}/{scene}/spp{spp}/ (as denoise_clip's outputs)
#   evaluate_volume: <output_dir>/volumes/metrics/{method}/{scene}/spp{spp}.csv + .json (per-frame metrics)
#   robustness_volume: <output_dir>/volumes/robustness/{method}/{scene}/spp{spp}/ (spikes and NaN/Inf injected;
#                    rows with robustness: true, at evaluation.robustness.spp)
# build_report reads them for the Iglesias-Guitian section (denoisers.reproductions.iglesias2022).


rule denoise_volume:
    input:
        valid=check_volume_target("denoise_volume", "volumes/denoised/{method}/{scene}/spp{spp}"),
        noisy=scene_chunk_dirs("noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
    output:
        out_dir=directory(results_path("volumes/denoised/{method}/{scene}/spp{spp}")),
    params:
        config_file=resolved_config_file,
        config_digest=denoise_digest,
        render_dir=render_dir,
        results=results_root,
    log:
        results_path("logs/denoise_volume/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/denoise_volume/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=30,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers denoise --config {params.config_file} --method-id {wildcards.method}"
        " --scene {wildcards.scene} --spp {wildcards.spp} --render-dir {params.render_dir}"
        " --results {params.results} --out {output.out_dir} --threads {threads} > {log} 2>&1"


rule evaluate_volume:
    input:
        valid=check_volume_target("evaluate_volume", "volumes/metrics/{method}/{scene}/spp{spp}.csv"),
        denoised=results_path("volumes/denoised/{method}/{scene}/spp{spp}"),
        reference=scene_chunk_dirs("reference"),
    output:
        csv=results_path("volumes/metrics/{method}/{scene}/spp{spp}.csv"),
        sidecar=results_path("volumes/metrics/{method}/{scene}/spp{spp}.json"),
    params:
        config_file=resolved_config_file,
        config_digest=evaluate_digest,
        render_dir=render_dir,
    log:
        results_path("logs/evaluate_volume/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/evaluate_volume/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers evaluate --config {params.config_file}"
        " --denoised {input.denoised} --render-dir {params.render_dir} --out {output.csv} > {log} 2>&1"


rule robustness_volume:
    input:
        valid=check_volume_target("robustness_volume", "volumes/robustness/{method}/{scene}/spp{spp}", "robustness"),
        noisy=scene_chunk_dirs("noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
        reference=scene_chunk_dirs("reference"),
    output:
        out_dir=directory(results_path("volumes/robustness/{method}/{scene}/spp{spp}")),
    params:
        config_file=resolved_config_file,
        config_digest=robustness_digest,
        render_dir=render_dir,
        results=results_root,
    log:
        results_path("logs/robustness_volume/{method}/{scene}/spp{spp}.log"),
    benchmark:
        results_path("benchmarks/robustness_volume/{method}/{scene}/spp{spp}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=30,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers robustness --config {params.config_file} --method-id {wildcards.method}"
        " --scene {wildcards.scene} --spp {wildcards.spp} --render-dir {params.render_dir}"
        " --results {params.results} --out {output.out_dir} --threads {threads} > {log} 2>&1"
