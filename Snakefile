# rigbuild: capture session -> calibrated cameras -> reconstructed ROM -> tracked meshes ->
# personalized rig -> retargeted animation -> report.  `snakemake --cores 2` runs config/config.yaml.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "rules/common.smk"
include: "rules/synth.smk"
include: "rules/calibrate.smk"
include: "rules/reconstruct.smk"
include: "rules/track.smk"
include: "rules/personalize.smk"
include: "rules/characters.smk"
include: "rules/retarget.smk"
include: "rules/retarget_seol.smk"
include: "rules/retarget_actor_rig.smk"
include: "rules/eval.smk"
include: "rules/report.smk"


rule all:
    input:
        [results(s, "report.html") for s in SESSIONS],
    default_target: True
