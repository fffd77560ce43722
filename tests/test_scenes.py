"""Every scene in scenes/ documents itself, and loads and renders (finite,
non-negative, not black) with every estimator that reaches what its header
says it contains. (The others must refuse it: test_refusals.py.)"""

import numpy as np
import pytest

from mcillum.integrators.core import registry
from mcillum.validation.plan import scenes
from mcillum.validation.run import renders

from conftest import ALL_ESTIMATORS

SCENES = scenes.index()


def test_every_scene_documents_itself():
    for info in SCENES.values():
        text = open(info.path, encoding="utf-8").read()
        assert info.summary.startswith(f"{info.name}:"), info.path
        for word in ("Tests:", "Why nothing more:", "Parameters:"):
            assert word in text, f"{info.path}: header lacks '{word}'"
        assert "Estimators:" not in text, f"{info.path}: estimators come from the registry"


CASES = [(s, e) for s, info in SCENES.items() for e in [*ALL_ESTIMATORS, "path"]
         if registry.facts(e).renders(info.contains)]


@pytest.mark.parametrize("scene, estimator", CASES)
def test_scene_renders_finite(llvm, scene, estimator):
    loaded = renders.load_scene(SCENES[scene].path, res=8)
    integrator = renders.make_integrator(estimator)
    for spp in (1, 4):
        image = renders.render(loaded, integrator, spp).image
        assert np.isfinite(image).all() and image.min() >= 0
    assert image.max() > 0


def test_scene_index_refuses_undocumented_scenes(tmp_path):
    (tmp_path / "bare.xml").write_text('<scene version="3.0.0"/>')
    with pytest.raises(ValueError, match="no header comment"):
        scenes.index(str(tmp_path))


def test_scene_index_refuses_unknown_content_kinds(tmp_path):
    (tmp_path / "odd.xml").write_text('<!--\n  odd: a scene.\n\n  Contains: lasers\n-->\n'
                                      '<scene version="3.0.0"/>')
    with pytest.raises(ValueError, match="'Contains:' names lasers"):
        scenes.index(str(tmp_path))
