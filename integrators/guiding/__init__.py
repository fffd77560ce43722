"""A pdf learned while rendering: ``guided_path`` (the integrator) and
``guide`` (the tree over the scene it learns, and its distributions)."""
