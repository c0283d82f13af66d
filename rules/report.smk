# The session report: one self-contained HTML file per session (images embedded).


rule report:
    """Metrics with pass/warn/fail, the stages' pictures and rule timings, in one HTML file."""
    input:
        lambda wc: stage_targets(wc.session),
    output:
        html=report("results/{session}/report.html", category="Report",
                    caption="../workflow/report/session_report.rst"),
    params:
        results_dir=lambda wc: results(wc.session),
        thresholds=lambda wc: config["params"]["report"].get("thresholds", {}),
    log:
        "logs/{session}/report/report.log",
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../environment.yml"
    script:
        "../scripts/report.py"
