"""Every scene in scenes/ loads and renders with every estimator it declares
(finite, non-negative), and is refused by those its header says must refuse."""

import numpy as np
import pytest

from mcillum.integrators import UnreachableContentError
from mcillum.validation import renders, scenes

SCENES = scenes.index()


def test_every_scene_documents_itself():
    for info in SCENES.values():
        text = open(info.path, encoding="utf-8").read()
        assert info.summary.startswith(f"{info.name}:"), info.path
        for word in ("Tests:", "Why nothing more:", "Parameters:"):
            assert word in text, f"{info.path}: header lacks '{word}'"
        assert "path" in info.estimators, f"{info.path}: no reference integrator"


CASES = [(s, e) for s, info in SCENES.items() for e in info.estimators]


@pytest.mark.parametrize("scene, estimator", CASES)
def test_scene_renders_finite(llvm, scene, estimator):
    loaded = renders.load_scene(SCENES[scene].path, res=8)
    integrator = renders.make_integrator(estimator)
    for spp in (1, 4):
        image = renders.render(loaded, integrator, spp).image
        assert np.isfinite(image).all() and image.min() >= 0
    assert image.max() > 0


REFUSALS = [(s, e) for s, info in SCENES.items() for e in info.refused_by]


@pytest.mark.parametrize("scene, estimator", REFUSALS)
def test_scene_is_refused(llvm, scene, estimator):
    loaded = renders.load_scene(SCENES[scene].path, res=2)
    with pytest.raises(Exception) as info:
        renders.render(loaded, renders.make_integrator(estimator), 1)
    assert isinstance(renders.root_cause(info.value), UnreachableContentError)


def test_scene_index_refuses_undocumented_scenes(tmp_path):
    (tmp_path / "bare.xml").write_text('<scene version="3.0.0"/>')
    with pytest.raises(ValueError, match="no header comment"):
        scenes.index(str(tmp_path))
