"""mcillum validation: compare the estimators with Mitsuba's path tracer.

Read it as the pipeline it runs; each module imports only modules above it:

    profiles, scenes        what to run: scenes, resolutions, spp, K, failure cases
    seeds                   which seed every render uses (disjoint named streams)
    metrics, results        the error metrics, and the typed records of a run
                            (with its files: results.json, csv, summary, JUnit)
    images, renders,        one render, timed; K renders per estimator and spp
    sweeps
    costs, timing           t = a + b·spp with intervals, efficiency, ranking;
                            timed warm renders (and `mcillum bench`)
    statistics, references  batch-means tests; Mitsuba's `path` until its noise is small
    tails, analysis         heavy tails; metrics per spp, convergence
    checks                  every check and verdict rule
    context, stages, speed  one scene run or failure case, the stages over it, and
                            the speed-and-images stage at the display resolution
    charts, report          what people look at
    progress, pipeline      the one orchestrator (`mcillum validate`)
    cli                     the `mcillum` command
"""
