# The session's metrics (one file gathered from every job's fragment) and its report.
from rigbuild.retarget.params import ribera_from_config


rule metrics:
    """Gather every metrics fragment of a session (stage jobs and ground-truth evaluation) into metrics.json."""
    input:
        lambda wc: metric_files(wc.session),
    output:
        metrics="results/{session}/metrics.json",
    log:
        "logs/{session}/report/metrics.log",
    threads: 1
    resources:
        mem_mb=500,
    conda:
        "../environment.yml"
    script:
        "../scripts/metrics.py"


rule report:
    """The decision page: per-stage pass/warn/fail with limits, the stages' pictures, a 3D view of the
    personalized rig and of every retargeted take on its character (three.js inlined: run
    `python -m rigbuild.assets.web install` once), metrics and rule timings, in one HTML file."""
    input:
        metrics="results/{session}/metrics.json",
        stages=lambda wc: stage_targets(wc.session),
        characters=lambda wc: [results(wc.session, "characters", f"{c}.npz") for c in CHARACTERS],
    output:
        html=report("results/{session}/report.html", category="Report",
                    caption="../workflow/report/session_report.rst"),
        # the 3D view's data and three.js when the page would exceed params.report.inline_limit_mb inline
        assets=directory("results/{session}/report_files"),
    params:
        results_dir=lambda wc: results(wc.session),
        report=lambda wc: config["params"]["report"],
        primary=lambda wc: ribera_from_config(config["params"]["retarget"].get("ribera", {})).primary,
    log:
        "logs/{session}/report/report.log",
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../environment.yml"
    script:
        "../scripts/report.py"
