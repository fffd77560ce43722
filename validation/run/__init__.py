"""Rendering for a validation: one render timed honestly (renders.py), a
render as data another process can run (jobs.py), stacks of K renders kept
in the run directory (stacks.py), `path` references rendered only as far as
needed (references.py), where the renders run (executors.py,
ray_executor.py), timed warm renders and `mcillum bench` (timing.py), the
progress line (progress.py) and Mitsuba's log during a run (mitsuba_log.py)."""
