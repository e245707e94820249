"""prsa_ctrl.studies.sceneloops: the pipeline's LoopSpec is internal; the studies package's public
name of it is deprecated."""

import pytest


def test_the_studies_package_name_of_the_loop_spec_is_deprecated():
    import prsa_ctrl.studies as studies
    from prsa_ctrl.studies.sceneloops import LoopSpec

    assert "LoopSpec" not in studies.__all__
    with pytest.warns(DeprecationWarning, match="prsa_ctrl.studies.LoopSpec is deprecated"):
        assert studies.LoopSpec is LoopSpec
    with pytest.warns(DeprecationWarning):  # every read warns (the name is not cached in the package)
        assert studies.LoopSpec is LoopSpec
