# Synthetic capture sessions: one generator rule per session whose config entry has a `synthetic:`
# block. The generator writes the whole session folder (calibration board images, ROM images, marker
# performances, ground_truth/) and renames it into place at the end; session.yaml stands for it.

for _s in SESSIONS:
    if not is_synthetic(_s):
        continue

    rule:
        name:
            f"synth_session_{_s}"
        output:
            synthetic_files(_s),
        params:
            session=_s,
            synthetic=config["sessions"][_s]["synthetic"],
            folder=lambda wc, output: os.path.dirname(output[0]),
        log:
            f"logs/{_s}/synth/synth_session.log",
        benchmark:
            f"results/{_s}/benchmarks/synth_session.tsv"
        threads: 1
        resources:
            mem_mb=4000,
        conda:
            "../environment.yml"
        script:
            "../scripts/synth_session.py"
