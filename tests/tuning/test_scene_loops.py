"""prsa_ctrl.tuning.scene_loops: the deprecated alias of prsa_ctrl.tuning.actuatorloops warns and
hands over the module's own functions."""

import pytest

from prsa_ctrl.tuning import actuatorloops, scene_loops


@pytest.mark.parametrize("name", scene_loops.__all__)
def test_every_name_warns_and_is_the_actuator_loops_one(name):
    with pytest.warns(DeprecationWarning, match=f"scene_loops is deprecated; import {name} from "
                                                "prsa_ctrl.tuning.actuatorloops"):
        assert getattr(scene_loops, name) is getattr(actuatorloops, name)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        scene_loops.nope  # noqa: B018
