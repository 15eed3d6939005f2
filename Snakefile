# Monte Carlo denoising reference harness: seeded procedural scenes -> Mitsuba 3 noisy per-sample
# renders and high-spp references (OpenEXR). Rules live in workflow/rules/, the config schema in
# workflow/schemas/config.schema.yaml. Stage targets: `snakemake scenes`, `snakemake renders`.

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/scenes.smk"
include: "workflow/rules/render.smk"


localrules:
    all,
    scenes,
    renders,


rule scenes:
    input:
        scene_dirs(),


rule renders:
    input:
        chunk_dirs("noisy"),
        chunk_dirs("reference"),


# Everything implemented so far; the default target.
rule all:
    default_target: True
    input:
        rules.scenes.input,
        rules.renders.input,
