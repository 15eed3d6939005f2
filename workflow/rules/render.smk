# Stage 2: Mitsuba 3 renders per (scene, chunk of frames).
#   noisy:     <output_dir>/renders/{scene}/noisy/chunk_{chunk}/frame_{t:04d}.exr + .json
#   reference: <output_dir>/renders/{scene}/reference/chunk_{chunk}/frame_{t:04d}.exr + .json
# {chunk} is the zero-padded chunk index (000, 001, ...); the CLI gets it as an integer.
# An evaluated scene's reference chunk stored under its render digest (store.references; scenegen.reference_store)
# is copied from the store by the render_reference job instead of rendered.


rule render_noisy:
    input:
        valid=check_chunk_target("noisy"),
        scene_dir=results_path("scenes/{scene}"),
    output:
        chunk_dir=directory(results_path("renders/{scene}/noisy/chunk_{chunk}")),
    params:
        config_file=resolved_config_file,
        config_digest=render_digest("noisy"),
        chunk=lambda wildcards: int(wildcards.chunk),
    log:
        results_path("logs/render_noisy/{scene}/chunk_{chunk}.log"),
    benchmark:
        results_path("benchmarks/render_noisy/{scene}/chunk_{chunk}.tsv")
    conda:
        "../envs/harness.yaml"
    # Scenes and renders first (priority above every other rule): a 2-thread render starts only when both
    # cores are free, which seldom happens once 1-thread trainings run (Snakemake's greedy scheduler fills a
    # free core and reserves none), so a render left for later held back the training that needed it (in the
    # default run of 2026-12-02 rae_volume's volumetric renders came last and it trained alone for 45 min with
    # one core idle). Once every scene exists, a finished render frees both cores for the next one.
    priority: 10
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m scenegen render-noisy --config {params.config_file} --scene {wildcards.scene}"
        " --chunk {params.chunk} --scene-dir {input.scene_dir} --out {output.chunk_dir} --threads {threads} > {log} 2>&1"


rule render_reference:
    input:
        valid=check_chunk_target("reference"),
        scene_dir=results_path("scenes/{scene}"),
    output:
        chunk_dir=directory(results_path("renders/{scene}/reference/chunk_{chunk}")),
    params:
        config_file=resolved_config_file,
        config_digest=render_digest("reference"),
        chunk=lambda wildcards: int(wildcards.chunk),
    log:
        results_path("logs/render_reference/{scene}/chunk_{chunk}.log"),
    benchmark:
        results_path("benchmarks/render_reference/{scene}/chunk_{chunk}.tsv")
    conda:
        "../envs/harness.yaml"
    # Scenes and renders first (priority above every other rule): a 2-thread render starts only when both
    # cores are free, which seldom happens once 1-thread trainings run (Snakemake's greedy scheduler fills a
    # free core and reserves none), so a render left for later held back the training that needed it (in the
    # default run of 2026-12-02 rae_volume's volumetric renders came last and it trained alone for 45 min with
    # one core idle). Once every scene exists, a finished render frees both cores for the next one.
    priority: 10
    threads: 2
    resources:
        mem_mb=4000,
        runtime=240,
        **gpu_resources(),   # compute.device cuda: a GPU (and MCDN_SLURM_GPU_PARTITION)
    shell:
        "python -m scenegen render-reference --config {params.config_file} --scene {wildcards.scene}"
        " --chunk {params.chunk} --scene-dir {input.scene_dir} --out {output.chunk_dir} --threads {threads} > {log} 2>&1"
