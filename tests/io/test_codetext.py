"""prsa_ctrl.io.codetext: the C and Structured Text emitters commit one sample's states from one
table (``state_moves``), so the two cannot drift apart."""

from __future__ import annotations

import re

import pytest

from prsa_ctrl.io.codegen import c_code, st_code
from prsa_ctrl.io.codetext import ENABLE_GATE, state_moves
from test_codegen import _variants


def _c_commit(src: str) -> list:
    """The C commit as [[(state, value), ...] | "GATE"], names made canonical."""
    lines = [ln.strip() for ln in src[src.index("/* commit */") + len("/* commit */"):].split("\n") if ln.strip()]
    assert lines[-2:] == ["return s->u_out;", "}"]
    lines, out, i = lines[:-2], [], 0
    while i < len(lines):
        if lines[i] == "if (!enable) {":
            assert lines[i:i + 4] == ["if (!enable) {", "prsa_ctrl_off_(s);", "return s->u_out;", "}"]
            out.append("GATE")
            i += 4
            continue
        out.append([tuple(_c_canon(x.strip()) for x in m.split(" = ")) for m in lines[i].rstrip(";").split("; ")])
        i += 1
    return out


def _c_canon(x: str) -> str:
    m = re.fullmatch(r"s->(sf|tf)\[(\d+)\]\[(\d)\]", x)
    if m:
        return f"{m[1]}{m[2]}.{m[3]}"
    m = re.fullmatch(r"(sy|ty)\[(\d+)\]", x)
    if m:
        return f"{m[1]}{m[2]}"
    return x.replace("s->", "state.") if x.startswith("s->") else "now." + x


#: The ST names of the C ones (written here apart from the emitters' table: an independent key).
ST_TO_C = {"s_WFilt": "state.w_filt", "s_Deriv": "state.deriv", "s_WPrev": "state.w_prev", "Speed": "state.speed",
           "s_Integral": "state.integral", "s_Phase": "state.phase", "s_PIntegral": "state.p_integral",
           "s_WRef": "state.w_ref", "s_TauP": "state.tau_p", "CommandUnfiltered": "state.command_unfiltered",
           "s_UOut": "state.u_out", "s_UPending": "state.u_pending", "t_Wf": "now.wf", "t_Dv": "now.d", "t_W": "now.w",
           "t_Int": "now.integral", "t_Us": "now.us", "t_Uf": "now.uf", "t_Phase": "now.phase",
           "t_PIntegral": "now.p_integral", "t_WRef": "now.w_ref", "t_TauP": "now.tau_p"}


def _st_canon(x: str) -> str:
    if x in ST_TO_C:
        return ST_TO_C[x]
    m = re.fullmatch(r"s_(SF|TF)(\d+)_(X1|X2|Y1|Y2)", x)
    if m:
        return f"{m[1].lower()}{m[2]}.{['X1', 'X2', 'Y1', 'Y2'].index(m[3])}"
    m = re.fullmatch(r"t_(SF|TF)(\d+)", x)
    if m:
        return f"{'sy' if m[1] == 'SF' else 'ty'}{m[2]}"
    m = re.fullmatch(r"([st])_Pend([WT])(\d+)", x)
    assert m, x
    return f"state.pend_{m[2].lower()}{m[3]}" if m[1] == "s" else f"now.p{m[2].lower()}{m[3]}"


def _st_commit(st: str) -> list:
    lines = [ln.strip() for ln in st.split("\n")]
    lines = lines[lines.index("s_WFilt := t_Wf;"):]
    lines = lines[:len(lines) - 1 - lines[::-1].index("TorqueCmd := s_UOut;")]  # the last: the gate returns too
    out, i = [], 0
    while i < len(lines):
        if lines[i] == "IF NOT Enable THEN":
            i = lines.index("RETURN;", i) + 1  # (the return block holds an IF of its own)
            assert lines[i] == "END_IF;"
            i += 1
            out.append("GATE")
            continue
        out.append([tuple(_st_canon(x.strip()) for x in m.split(" := ")) for m in lines[i].rstrip(";").split("; ")])
        i += 1
    return out


@pytest.mark.parametrize("variant", tuple(_variants()))
def test_c_and_st_commit_the_same_moves_in_the_same_order(variant, paper_plant):
    """Each export's commit, read back from the generated C and from the generated ST and named
    alike by a key written apart from the emitters, is the same moves in the same order, with
    the enable check at the same place; and it is the table's."""
    law = _variants()[variant](paper_plant)
    c_moves = _c_commit(c_code(law)[1])
    st_moves = _st_commit(st_code(law))
    assert c_moves == st_moves
    ns, nt = len(law.speed_biquads), len(law.torque_biquads)
    table = state_moves(ns, nt, None if law.position is None else law.position.delay, law.delay_samples)
    assert len(table) == len(c_moves)
    assert [x == ENABLE_GATE for x in table] == [x == "GATE" for x in c_moves]
    assert any(isinstance(line, list) and len(line) == 4 for line in c_moves) == bool(ns + nt)


def test_the_table_is_what_each_law_needs():
    """Filters shift four slots each, the position loop moves its four states and a pair per delay
    sample, the torque delay decides what the output takes."""
    plain = state_moves(0, 0, None, 1)
    assert plain[0] == (("S.w_filt", "T.wf"),)
    assert plain.count(ENABLE_GATE) == 1
    assert plain[-2] == (("S.u_out", "S.u_pending"),)
    assert state_moves(0, 0, None, 0)[-2] == (("S.u_out", "T.uf"),)
    full = state_moves(2, 3, 2, 1)
    assert len(full) == len(plain) + 2 + 3 + 4 + 2
    assert (("S.pend_w2", "T.pw2"), ("S.pend_t2", "T.pt2")) in full
