# Stage 1: seeded procedural scenes (and imported custom XML scenes).
# Output layout: <output_dir>/scenes/{scene}/manifest.json, meshes/*.ply, textures/*.png


rule generate_scene:
    input:
        unpack(generate_scene_input),
    output:
        scene_dir=directory(results_path("scenes/{scene}")),
    params:
        config_file=resolved_config_file,
        config_digest=generate_scene_digest,
    log:
        results_path("logs/generate_scene/{scene}.log"),
    benchmark:
        results_path("benchmarks/generate_scene/{scene}.tsv")
    conda:
        "../envs/harness.yaml"
    # With the renders, ahead of every other rule: every scene exists before the renders start, so they
    # run back to back on both cores (see render.smk).
    priority: 10
    threads: 1
    resources:
        mem_mb=4000,
        runtime=20,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m scenegen generate --config {params.config_file} --scene {wildcards.scene}"
        " --out {output.scene_dir} > {log} 2>&1"
