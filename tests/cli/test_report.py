"""prsa_ctrl.cli.report: the deprecated alias of prsa_ctrl.studies.scenereport warns and hands over
the report module's own functions; prsa_ctrl.cli's names of them do not warn."""

import pytest

import prsa_ctrl.cli as cli
from prsa_ctrl.cli import report
from prsa_ctrl.studies import scenereport


@pytest.mark.parametrize("name", report.__all__)
def test_every_name_warns_and_is_the_scene_report_one(name):
    with pytest.warns(DeprecationWarning, match=f"cli.report is deprecated; import {name} from "
                                                "prsa_ctrl.studies.scenereport"):
        assert getattr(report, name) is getattr(scenereport, name)


@pytest.mark.parametrize("name", report.__all__)
def test_the_cli_package_names_are_the_report_module_s(name):
    assert getattr(cli, name) is getattr(scenereport, name)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        report.nope  # noqa: B018
