"""The numbers of a validation, as small pure functions of arrays: error
metrics (metrics.py), batch-means tests (statistics.py), heavy tails
(tails.py), cost models and efficiency (costs.py). No Mitsuba."""
