"""prsa_ctrl.studies.sceneloops: a scene read once (``loop_spec``: its kind's resolved problem) and
its loop models (``actuator_loops``)."""

import pytest

from prsa_ctrl.studies.kindruns import ResolvedProblem, speed_kind
from prsa_ctrl.studies.scene import load_scene
from prsa_ctrl.studies.sceneloops import actuator_loops, loop_spec


def test_the_loop_spec_mirror_is_gone_from_the_package():
    """Issue 33: ``LoopSpec`` (a copy of the scene's fields) is removed, not deprecated: it had left
    ``__all__`` and the API reference, and no documented import names it."""
    import prsa_ctrl.studies as studies
    import prsa_ctrl.studies.sceneloops as sceneloops

    assert not hasattr(sceneloops, "LoopSpec")
    with pytest.raises(AttributeError):
        studies.LoopSpec  # noqa: B018
    assert studies.ResolvedProblem is ResolvedProblem


def test_loop_spec_is_the_kinds_resolution_without_choosing_the_fidelity(paper_plant):
    scene = load_scene().replace(fidelity="auto")
    spec = loop_spec(paper_plant, scene)
    ref = speed_kind(scene).resolve(paper_plant, choose=False)
    assert spec == ref
    assert spec.scene is scene
    assert spec.scene.fidelity == "auto"
    assert spec.linear_fidelity == "compliant"


def test_actuator_loops_are_the_resolved_problems_loop_models(paper_plant):
    scene = load_scene("paper-table3").replace(fidelity="rigid")
    loops = actuator_loops(paper_plant, scene)
    again = loop_spec(paper_plant, scene).loop_models(paper_plant)
    assert [lp.name for lp in loops] == [lp.name for lp in again]
    assert len(loops) == len(scene.final_loads)
    for a, b in zip(loops, again):
        assert (a.error((0.08, 14.0, 0.0)) == b.error((0.08, 14.0, 0.0))).all()
