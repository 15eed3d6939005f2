# Temporal-stability scenarios (scenegen/scenarios/, config section `stability`): scenes stab_{name} and the
# controls stab_{name}__still of the animated ones (held at their final frame) are generated and rendered by
# generate_scene, render_noisy and render_reference (one chunk per clip); this rule
# derives where and when each scenario's difficulty happens from those renders.
#   derive_masks:     <output_dir>/stability/{scene}/masks/frame_{t:04d}.exr + events.json
# Every configured row of evaluation.methods (not the ablation variants) then runs on every clip at
# stability.denoise_spp (denoisers.jobs.stability), one job per row for all its clips (denoisers.jobs.rows), and
# the failure atlas is built from the scores:
#   denoise_scenario_row: <output_dir>/stability/denoised/{method}/{scene}/spp{spp}/ (as denoise_row's outputs)
#   score_scenario_row:   <output_dir>/stability/scores/{method}/{scene}/spp{spp}.csv + .json (failure metrics; the
#                         lag metric's steady state from the scenario's failure-free control stab_{name}__still,
#                         denoised by the same row)
#   build_atlas:          <output_dir>/stability/ATLAS.md, stability/tables/, stability/figures/ (build_report links it)

rule derive_masks:
    input:
        valid=check_stability_target,
        scene_dir=results_path("scenes/{scene}"),
        noisy=scene_chunk_dirs("noisy"),
        reference=scene_chunk_dirs("reference"),
    output:
        masks_dir=directory(results_path("stability/{scene}")),
    params:
        config_file=resolved_config_file,
        config_digest=masks_digest,
        render_dir=render_dir,
    log:
        results_path("logs/derive_masks/{scene}.log"),
    benchmark:
        results_path("benchmarks/derive_masks/{scene}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=20,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m scenegen derive-masks --config {params.config_file} --scene {wildcards.scene}"
        " --scene-dir {input.scene_dir} --render-dir {params.render_dir} --out {output.masks_dir}"
        " --threads {threads} > {log} 2>&1"


rule denoise_scenario_row:
    input:
        valid=check_scenario_row_target("denoise_scenario_row", "stability/denoised/{method}"),
        noisy=chunk_dirs_of(STABILITY_SCENES + STABILITY_CONTROLS, "noisy"),
        model=method_model_dir,
        tuning=method_tuning_file,
    output:
        out_dir=directory(results_path("stability/denoised/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=denoise_digest,
        render_root=results_path("renders"),
        results=results_root,
    log:
        results_path("logs/denoise_scenario/{method}.log"),
    benchmark:
        results_path("benchmarks/denoise_scenario/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: config["evaluation"]["threads"]
    resources:
        mem_mb=4000,
        runtime=row_runtime(stability_run_list, STABILITY_SCENES + STABILITY_CONTROLS),
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m denoisers denoise-row --kind stability --config {params.config_file}"
        " --method-id {wildcards.method} --render-root {params.render_root} --results {params.results}"
        " --out {output.out_dir} --threads {threads} > {log} 2>&1"


rule score_scenario_row:
    input:
        valid=check_scenario_row_target("score_scenario_row", "stability/scores/{method}"),
        denoised=results_path("stability/denoised/{method}"),
        reference=chunk_dirs_of(STABILITY_SCENES + STABILITY_CONTROLS, "reference"),
        masks=stability_mask_dirs,
    output:
        out_dir=directory(results_path("stability/scores/{method}")),
    params:
        config_file=resolved_config_file,
        config_digest=scenario_score_digest,
        render_root=results_path("renders"),
        masks_root=masks_root,
    log:
        results_path("logs/score_scenario/{method}.log"),
    benchmark:
        results_path("benchmarks/score_scenario/{method}.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=row_runtime(stability_run_list, STABILITY_SCENES + STABILITY_CONTROLS),
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers score-scenarios-row --config {params.config_file}"
        " --denoised {input.denoised} --render-root {params.render_root} --masks-root {params.masks_root}"
        " --out {output.out_dir} > {log} 2>&1"


rule build_atlas:
    input:
        scores=scenario_outputs("scores"),
        denoised=scenario_outputs("denoised"),
        masks=stability_mask_dirs,
    output:
        markdown=ATLAS_OUTPUTS["markdown"],
        tables=ATLAS_OUTPUTS["tables"],
        figures=ATLAS_OUTPUTS["figures"],
    params:
        config_file=resolved_config_file,
        config_digest=atlas_digest,
        results=results_root,
    log:
        results_path("logs/build_atlas.log"),
    benchmark:
        results_path("benchmarks/build_atlas.tsv")
    conda:
        "../envs/harness.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
    shell:
        "OMP_NUM_THREADS={threads} python -m denoisers atlas --config {params.config_file}"
        " --results {params.results} > {log} 2>&1"
