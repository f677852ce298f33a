# refflow workbench: simulate -> render -> calibrate -> track -> evaluate -> report.
# Thin by design: configuration, schema validation, rule files, rule all.
from snakemake.utils import min_version, validate

min_version("8.0")


# `--configfile config/ci.yaml` replaces the default config instead of merging into it
# (scenario dicts would otherwise mix); `--config key=value` alone still reads the default.
if not workflow.overwrite_configfiles:

    configfile: "config/config.yaml"


validate(config, "workflow/schemas/config.schema.yaml")


include: "workflow/rules/common.smk"


wildcard_constraints:
    scenario="|".join(map(re.escape, SCENARIOS)),
    method="|".join(map(re.escape, METHODS + [m for s in SCENARIOS for m in scenario_methods(s)])),


include: "workflow/rules/simulate.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/track.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        all_outputs(),
        f"{RESULTS}/timings.md",
    default_target: True
