# Temporal-stability scenarios (scenegen/scenarios/, config section `stability`): scenes stab_{name} are
# generated and rendered by generate_scene, render_noisy and render_reference (one chunk per clip); this rule
# derives where and when each scenario's difficulty happens from those renders.
#   derive_masks: <output_dir>/stability/{scene}/masks/frame_{t:04d}.exr + events.json


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
    shell:
        "python -m scenegen derive-masks --config {params.config_file} --scene {wildcards.scene}"
        " --scene-dir {input.scene_dir} --render-dir {params.render_dir} --out {output.masks_dir}"
        " --threads {threads} > {log} 2>&1"
