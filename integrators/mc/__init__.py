"""The course's Monte Carlo estimators, one per file, each with its sampling
routine and pdf: uniform and cosine hemisphere sampling, BSDF sampling,
emitter sampling, and both combined by MIS (Mitsuba's ``path`` in our loop)."""
