"""Estimators of N directions per shading point (direct light only): the
randomized Fibonacci set (``fibonacci_hemisphere``), Bayesian quadrature on
it (``bayesian_hemisphere``) and Bayesian cubature where the light is
(``bayesian_importance``); the Gaussian-process weights (``gp_quadrature``),
the settings chosen per scene (``gp_settings``, ``gp_scene``)."""
