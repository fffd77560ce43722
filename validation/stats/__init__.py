"""The numbers of a validation, as small pure functions of arrays: error
metrics (metrics.py), batch-means tests (statistics.py) and their
replication on fresh renders (replication.py), heavy tails (tails.py),
cost models and efficiency (costs.py). No Mitsuba."""
