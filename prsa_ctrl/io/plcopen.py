"""The drive law's function block as PLCopen TC6 XML (``http://www.plcopen.org/xml/tc6_0201``).

TwinCAT and CODESYS do not import a bare ``.st`` file (declaration and body go into separate
panes); they import PLCopen XML (Import PLCopenXML). :func:`plcopen_xml` writes the block of
:func:`prsa_ctrl.io.codetext.st_code` as one ``pou`` of type ``functionBlock``: the interface as
typed variables (``inputVars``, ``outputVars``, ``localVars``) with initial values and
documentation, the body as ``<ST>`` text, the header (what the gains assume) as the block's
documentation. :func:`st_from_plcopen` rebuilds the Structured Text from the XML alone (the test
compiles it with matiec's ``iec2c``, the same path as the ``.st`` export).

User text reaches the file only as :func:`prsa_ctrl.io.codetext.inert_text` (printable ASCII
without markup characters), inside CDATA sections that cannot be closed early.
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET
from xml.sax.saxutils import quoteattr

from .codetext import st_parts
from .drivelaw import DriveLaw

__all__ = ["plcopen_xml", "st_from_plcopen", "TC6_NAMESPACE"]

#: The PLCopen TC6 XML namespace (version 2.01).
TC6_NAMESPACE = "http://www.plcopen.org/xml/tc6_0201"
_XHTML = "http://www.w3.org/1999/xhtml"
_KINDS = (("inputVars", "inputs"), ("outputVars", "outputs"), ("localVars", "locals"))


def _cdata(text: str) -> str:
    return "<![CDATA[" + text.replace("]]>", "]]]]><![CDATA[>") + "]]>"


def _doc(text: str, indent: str) -> str:
    return f'{indent}<documentation><xhtml:p>{_cdata(text)}</xhtml:p></documentation>'


def plcopen_xml(law: DriveLaw, *, name: str = "PrsaCtrl", real: str = "double",
                created: "_dt.datetime | None" = None) -> str:
    """The function block of :func:`prsa_ctrl.io.codetext.st_code` as a PLCopen TC6 XML project.

    Parameters
    ----------
    law : DriveLaw
    name : str
        Name of the function block (an IEC identifier, no keyword).
    real : {"double", "float"}
        ``LREAL`` or ``REAL``.
    created : datetime, optional
        ``creationDateTime`` of the file header (default: now, UTC; a fixed value gives
        reproducible files).

    Returns
    -------
    str
        UTF-8 XML text (ASCII only).
    """
    from .. import __version__

    parts = st_parts(law, name=name, real=real)
    when = (created or _dt.datetime.now(_dt.timezone.utc)).replace(microsecond=0).isoformat()
    out = ['<?xml version="1.0" encoding="utf-8"?>',
           f'<project xmlns="{TC6_NAMESPACE}" xmlns:xhtml="{_XHTML}">',
           f'  <fileHeader companyName="prsa-ctrl" productName="prsa-ctrl" productVersion={quoteattr(__version__)} '
           f'creationDateTime={quoteattr(when)}/>',
           f'  <contentHeader name={quoteattr(parts["name"])}>',
           '    <coordinateInfo>', '      <fbd><scaling x="1" y="1"/></fbd>', '      <ld><scaling x="1" y="1"/></ld>',
           '      <sfc><scaling x="1" y="1"/></sfc>', '    </coordinateInfo>', '  </contentHeader>',
           '  <types>', '    <dataTypes/>', '    <pous>',
           f'      <pou name={quoteattr(parts["name"])} pouType="functionBlock">', '        <interface>']
    for tag, key in _KINDS:
        out.append(f"          <{tag}>")
        for nm, typ, init, com in parts[key]:
            out.append(f"            <variable name={quoteattr(nm)}>")
            out.append(f"              <type><{typ}/></type>")
            if init is not None:
                out.append(f"              <initialValue><simpleValue value={quoteattr(init)}/></initialValue>")
            if com:
                out.append(_doc(com, "              "))
            out.append("            </variable>")
        out.append(f"          </{tag}>")
    out += ['        </interface>', '        <body>', '          <ST>',
            '            <xhtml:p>' + _cdata("\n".join(parts["body"]) + "\n") + '</xhtml:p>', '          </ST>',
            '        </body>', _doc("\n".join(parts["comment"]), "        "), '      </pou>', '    </pous>',
            '  </types>', '  <instances>', '    <configurations/>', '  </instances>', '</project>', '']
    return "\n".join(out)


def st_from_plcopen(text: str) -> str:
    """The Structured Text FUNCTION_BLOCK a PLCopen XML file written by :func:`plcopen_xml` holds,
    rebuilt from the XML alone (declarations from the typed variables, the body from ``<ST>``).

    Raises
    ------
    ValueError
        Not a TC6 project with exactly one function block with an ST body.
    """
    ns = {"p": TC6_NAMESPACE, "x": _XHTML}
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"PLCopen XML: {exc}; expected well-formed XML") from None
    pous = root.findall("p:types/p:pous/p:pou", ns)
    if root.tag != f"{{{TC6_NAMESPACE}}}project" or len(pous) != 1 or pous[0].get("pouType") != "functionBlock":
        raise ValueError("PLCopen XML: expected a TC6 project with one functionBlock pou")
    pou = pous[0]
    lines = [f"FUNCTION_BLOCK {pou.get('name')}"]
    for tag, kw in (("inputVars", "VAR_INPUT"), ("outputVars", "VAR_OUTPUT"), ("localVars", "VAR")):
        for block in pou.findall(f"p:interface/p:{tag}", ns):
            lines.append(kw)
            for var in block.findall("p:variable", ns):
                typ = list(var.find("p:type", ns))[0].tag.split("}")[1]
                init = var.find("p:initialValue/p:simpleValue", ns)
                lines.append(f"    {var.get('name')} : {typ}" + (f" := {init.get('value')}" if init is not None else "")
                             + ";")
            lines.append("END_VAR")
    body = pou.find("p:body/p:ST/x:p", ns)
    if body is None or not (body.text or "").strip():
        raise ValueError("PLCopen XML: the function block has no ST body")
    return "\n".join(lines + ["", body.text.rstrip(), "END_FUNCTION_BLOCK", ""])
