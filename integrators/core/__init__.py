"""What the plugins share: the loop of every estimator (``estimator``) and
that of the estimators of N directions per point (``direction_set``), the
facts the validation reads (``registry``), what a scene holds that a strategy
cannot reach (``scene_checks``), and renders beyond 2³² samples (``passes``).

Nothing here registers a plugin. This file imports nothing: the LLVM set-up
(``.._llvm``) must run before the first ``import drjit``.
"""
