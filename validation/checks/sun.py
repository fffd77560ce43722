"""The rules of evidence read on a map with a sun (envmaps/sun.py; the sun
split: stages/sun_split.py).

A sun not yet seen is a tail too (:func:`unseen_sun`): no downward
rejection counts while the estimator's largest pdf allows fewer than
:data:`SUN_HITS` direct hits per pixel. On the map with its sun widened to
a disc (:func:`partly_hidden`), pixels that see the disc only through a
sliver are dark until its hits reach them: no downward pixel rejection
counts there, and the image mean decides.
"""

from __future__ import annotations

import numpy as np

from .evidence import Decision

#: Below this many expected direct sun hits per pixel, K renders cannot tell
#: a missed sun from a bias (see envmaps/sun.py).
SUN_HITS = 3.0


def unseen_sun(d: Decision, c, hits: float | None) -> Decision:
    """``d`` read with a sun the renders may not have hit yet (``hits``: the
    direct hits per pixel the estimator's largest pdf allows so far; None:
    no bound): no downward rejection counts — a missed sun only darkens —
    so a fail that rested on one becomes inconclusive, and a confirming
    batch does not count one either."""
    up = np.asarray(c.pooled_t) > 0
    d.pooled = None if d.pooled is None else d.pooled & up
    d.pixels = None if d.pixels is None else d.pixels & (np.nan_to_num(c.pixel_t) > 0)
    d.tail_pixels = np.ones(np.shape(c.pixel_p), bool)
    if d.outcome == "fail" and not d.counted_up:
        d.outcome = "inconclusive"
        d.reason += ("; the sun may be unseen: " +
                     (f"its largest pdf allows {hits:.2g} direct hits per pixel so far "
                      f"(fewer than {SUN_HITS:g})" if hits is not None else
                      "its facts give no largest pdf (max_direction_pdf)"))
    return d


def partly_hidden(d: Decision, c) -> Decision:
    """``d`` read for a bright source the samples hit often over the image
    but that some pixels see only through a sliver (the widened sun,
    stages/sun_split.py): such a pixel is darker, and holds no firefly, until
    the sliver's hits reach it, while the rest of the image shows no tail
    (probe_spheres under city, seed set 5: one pixel at 6 % of the
    reference after 4 096 samples of BSDF sampling). No downward pixel
    rejection counts; the image mean still counts both ways, so a clamp or a
    pdf that darkens the source fails. A fail that rested on such pixels
    becomes inconclusive, and the test renders on; where they are the only
    rejections, the image mean decides (a pass, then held to ±ε)."""
    d.pixels = None if d.pixels is None else d.pixels & (np.nan_to_num(c.pixel_t) > 0)
    if d.outcome == "fail" and not d.counted_up and not (d.pooled is not None
                                                         and d.pooled.any()):
        d.outcome = "inconclusive"
        d.reason += ("; darker pixels of a source they may see only through a sliver "
                     "do not count before its hits reach them")
    rejected = c.pixel_p < c.alpha_pixel
    only_down = not (rejected & (np.nan_to_num(c.pixel_t) >= 0)).any() \
        and not (np.asarray(c.pooled_p) < c.alpha_pooled).any()
    if d.outcome == "inconclusive" and only_down and rejected.any():
        d.outcome, d.samples_needed = "pass", None     # (settle holds it to ±ε)
    return d
