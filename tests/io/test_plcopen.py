"""PLCopen XML export (prsa_ctrl.io.plcopen, issue 36): the function block as TwinCAT and CODESYS
import it, parsed back, rebuilt as Structured Text from the XML alone and compiled by matiec's
iec2c; its C equals the toolkit's C bit for bit on a hostile sequence."""

from __future__ import annotations

import datetime
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from prsa_ctrl.io.codegen import drive_law, export_code, st_code
from prsa_ctrl.io.plcopen import TC6_NAMESPACE, plcopen_xml, st_from_plcopen
from test_codegen import (CC, FILTERS, HOSTILE_NAMES, MOVE_PID, SPEED_PID, PositionLoop, _build, _build_st, _drive,  # noqa: F401
                          _hostile, _variants, iec2c, matiec)

NS = {"p": TC6_NAMESPACE, "x": "http://www.w3.org/1999/xhtml"}
WHEN = datetime.datetime(2026, 1, 2, 3, 4, 5, tzinfo=datetime.timezone.utc)


def test_structure_as_tc6(paper_plant):
    law = drive_law(SPEED_PID, paper_plant, filters=FILTERS, position=PositionLoop(kv=102.7, kvff=1.0, kaff=1.0))
    text = plcopen_xml(law, name="Axis", created=WHEN)
    root = ET.fromstring(text)
    assert root.tag == f"{{{TC6_NAMESPACE}}}project"
    assert root.find("p:fileHeader", NS).get("creationDateTime") == "2026-01-02T03:04:05+00:00"
    pou = root.find("p:types/p:pous/p:pou", NS)
    assert pou.get("name") == "Axis" and pou.get("pouType") == "functionBlock"
    names = [v.get("name") for v in pou.findall("p:interface/p:inputVars/p:variable", NS)]
    assert names[:4] == ["Reset", "Enable", "Hold", "EncCount"] and "P_KP" in names
    kp = pou.find("p:interface/p:inputVars/p:variable[@name='P_KP']", NS)
    assert list(kp.find("p:type", NS))[0].tag == f"{{{TC6_NAMESPACE}}}LREAL"
    assert float(kp.find("p:initialValue/p:simpleValue", NS).get("value")) == law.kp
    doc = pou.find("p:documentation/x:p", NS).text
    assert "current-loop bandwidth" in doc and "if the drive's rates differ" in doc
    assert all(ord(c) < 128 for c in text)
    # the ST rebuilt from the XML is the .st export without its comments
    import re

    def lines(t):
        return [s.strip() for s in re.sub(r"\s*\(\*.*?\*\)", "", t, flags=re.S).splitlines() if s.strip()]

    assert lines(st_from_plcopen(text)) == lines(st_code(law, name="Axis"))


@pytest.mark.parametrize("real", ("double", "float"))
@pytest.mark.parametrize("variant", ("speed_pid_filters", "cascade_scale_filters", "cascade_friction"))
def test_xml_compiles_through_iec2c_and_equals_the_c(variant, real, paper_plant, matiec, tmp_path):
    law = _variants()[variant](paper_plant)
    st = st_from_plcopen(plcopen_xml(law, name="StCtrl", real=real))
    lib = _build_st(matiec, law, tmp_path / "st", real, text=st)
    seq = _hostile(law)
    u_x, f_x = _drive(lib, seq)
    u_c, f_c = _drive(_build(law, tmp_path, real), seq)
    np.testing.assert_array_equal(u_x, u_c)
    np.testing.assert_array_equal(f_x, f_c)


@pytest.mark.parametrize("hostile", HOSTILE_NAMES)
def test_hostile_plant_name_in_xml(hostile, paper_plant, matiec, tmp_path):
    """The XML with a hostile plant name is well formed, its documentation holds the name only
    in inert form, and the body compiles."""
    from prsa_ctrl.io.codetext import inert_text

    law = drive_law(SPEED_PID, paper_plant.with_params({}, name=hostile), filters=FILTERS)
    text = plcopen_xml(law, name="Ax")
    root = ET.fromstring(text)
    assert len(root.findall("p:types/p:pous/p:pou", NS)) == 1
    doc = root.find("p:types/p:pous/p:pou/p:documentation/x:p", NS).text
    assert inert_text(hostile) in doc and (hostile == inert_text(hostile) or hostile not in doc)
    iec2c(matiec, st_from_plcopen(text), tmp_path / "iec")


def test_bad_xml_is_refused():
    with pytest.raises(ValueError, match="expected well-formed XML"):
        st_from_plcopen("<project")
    with pytest.raises(ValueError, match="one functionBlock"):
        st_from_plcopen(f'<project xmlns="{TC6_NAMESPACE}"/>')


def test_export_code_and_cli_write_xml(paper_plant, tmp_path, matiec):
    f = export_code(SPEED_PID, paper_plant, tmp_path / "Speed.xml", real="float")
    assert [p.name for p in f] == ["Speed.xml"]
    assert "<REAL/>" in f[0].read_text() and "<LREAL/>" not in f[0].read_text()
    from prsa_ctrl.cli.tune import main

    out = tmp_path / "Axis.xml"
    assert main(["--scene", "paper-move", "--quiet", "--export", str(out)]) == 0
    iec2c(matiec, st_from_plcopen(out.read_text()), tmp_path / "iec")
