"""The report: one self-contained HTML page of a run (:func:`build`).

:mod:`.page` (the page and its header), :mod:`.scenes` (a scene
comparison's section), :mod:`.failures` (where methods fail), :mod:`.charts`
(SVG charts), :mod:`.parts` (images, numbers and swatches as HTML).
"""

from .page import build  # noqa: F401
