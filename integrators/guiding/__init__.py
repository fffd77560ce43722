"""A pdf learned while rendering: ``guided_path`` (the plugin) and what it
learns, one small piece per module, as Practical Path Guiding's classes:
``spatial`` (the voxel grid, anchors and guide frame), ``guide`` (the
spatial tree and its leaves' densities), ``directional`` (each leaf's
quadtree of cell means), ``records`` (what training paths leave, and their
sums), ``tables`` (what the kernel samples from), ``moments`` (pixels'
moments: whether a density paid, and each image's weight), ``trainer``
(the iterations of one render)."""
