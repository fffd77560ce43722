"""mcillum validation: compare the estimators with Mitsuba's path tracer.

A run reads as a pipeline: **plan** (what to run) → **run** (renders and the
reference) → **stats** (numbers) → **stages** (what each step of a scene
comparison or a failure case measures) → **checks** (the verdicts) →
**results** (records and their files) → **report** (what people look at).
``pipeline`` strings them together; ``cli`` is the ``mcillum`` command
(``arguments``: its parsers).

Imports point down the table below: a module imports only modules of its
own row or of rows beneath it, and never in a cycle. Two rows sit lower
than the reading order says: the stages ask the checks' rules of evidence
whether to render on (sequential tests), so checks sit below stages; and every layer
builds or reads records, so results sit near the bottom.
tests/test_layout.py reads this table and fails on an import that breaks it.

Layers, top to bottom:

    testing pytest_plugin  a user's tests: the comparison as a function, a pytest plugin
    validation.cli validation.arguments   the `mcillum` command: parses arguments, calls the library
    validation.pipeline   the orchestrator: stage lists, checks, results, report
    validation.report     the HTML page, its charts and its image parts
    validation.stages     context; scene comparison, failure cases, sequential tests, speed, quadrature
    validation.checks     the rules of evidence and every check
    validation.run        renders, jobs, stacks of K renders, references, executors, timing
    validation.stats      metrics, statistics, tails, costs: numbers, no Mitsuba
    validation.results    records; results.json, csv, summary.md, JUnit; the run directory
    validation.plan       profiles, scenes, seeds
    validation            this package (this docstring)
    mcillum               the front door: LLVM set-up and plugin registration
    integrators           the plugins by family (core, mc, quadrature, guiding, bsdfs)
    envmaps               environment maps: probes, procedural maps, the loading policy
    errors files images plugins   mcillum's own helpers: errors, files, tone mapping, users' plugins
"""
