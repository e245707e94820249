"""prsa_ctrl.plant.writer: the one plant-file writer (Plant.to_toml, document_toml)."""

from __future__ import annotations

import tomllib
import warnings

import pytest

from prsa_ctrl.plant.plantfile import Plant, builtin_plants, load_plant, plant_file_path
from prsa_ctrl.plant.writer import FRESH_NOTE, document_toml, inline_value, plant_toml, toml_string

HOSTILE = 'ev"il\\ \x1b]0;title\x07 \n\r\t \u202e µ \x7f \x85 end'


def _load(text: str) -> Plant:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Plant.from_dict(tomllib.loads(text), origin="written")


def _plant(name: str) -> Plant:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant(name)


@pytest.mark.parametrize("name", builtin_plants())
def test_every_builtin_plant_reads_back_from_its_own_file(name):
    p = _plant(name)
    q = _load(p.to_toml())
    assert dict(q.values) == dict(p.values)
    assert dict(q.sources) == dict(p.sources)
    assert q.uncertainty == p.uncertainty
    assert (q.name, q.description, q.mechanism) == (p.name, p.description, p.mechanism)


def _given_float_key(p: Plant) -> str:
    return next(k for k in p.values if p.given(k) and isinstance(p.values[k], float) and p.values[k] > 0
                and "inertia" in k)


@pytest.mark.parametrize("name", builtin_plants())
def test_base_layout_and_comments_kept_only_the_key_changes(name):
    p = _plant(name)
    base = plant_file_path(name).read_text(encoding="utf-8")
    key = _given_float_key(p)
    fitted = p.with_params({key: p.values[key] * 1.0123456789})
    text = fitted.to_toml(base, name="fitted", keys=[key], description="new description")
    q = _load(text)
    assert q.values[key] == fitted.values[key]
    assert (q.name, q.description) == ("fitted", "new description")
    for k in p.values:  # every other given key as in the base
        if k != key and p.given(k):
            assert (q.values[k], q.sources[k]) == (p.values[k], p.sources[k]), k
    comments = [ln for ln in base.splitlines() if ln.lstrip().startswith("#")]
    assert comments
    assert all(c in text.splitlines() for c in comments)  # every comment line kept
    assert FRESH_NOTE not in text
    # only the lines of the name, the description and the key differ
    changed = [ln for ln in text.splitlines() if ln not in base.splitlines()]
    assert len(changed) == 3, changed


@pytest.mark.parametrize("header", [(), ("prsa-fit --force: a forced file",)])
def test_a_crlf_base_gives_a_crlf_file_with_the_same_values_and_comments(header):
    name = builtin_plants()[0]
    p = _plant(name)
    base_lf = plant_file_path(name).read_text(encoding="utf-8")
    base = base_lf.replace("\n", "\r\n")
    key = _given_float_key(p)
    fitted = p.with_params({key: p.values[key] * 1.0123456789})
    text = fitted.to_toml(base, name="fitted", keys=[key], header=header)
    lf = fitted.to_toml(base_lf, name="fitted", keys=[key], header=header)
    assert text.count("\n") == text.count("\r\n") > 0  # every line CR LF, none bare
    assert text == lf.replace("\n", "\r\n")  # the same file as from the LF base, line endings aside
    assert _load(text).values[key] == fitted.values[key]


def test_a_base_with_mixed_line_endings_is_written_with_lf():
    name = builtin_plants()[0]
    base = plant_file_path(name).read_text(encoding="utf-8").replace("\n", "\r\n", 1)
    text = _plant(name).to_toml(base, name="x")
    assert text.count("\r\n") < text.count("\n")  # not made CR LF throughout: only a CR LF base is
    assert _load(text).values == _plant(name).values


def test_other_toml_spellings_of_a_key_are_edited_in_place():
    base = ('# header\nname = "b"\n\n[nut]\n# the nut\ninertia_kg_m2.value = 2.0e-4\n'
            'inertia_kg_m2.source = "catalogue"  # kept\n\n[nut.sub_table_like]\n')
    doc = tomllib.loads(base)
    want = {**doc, "nut": {**doc["nut"], "inertia_kg_m2": {"value": 1.5e-4, "source": "fit"}}}
    text = document_toml(want, base)
    assert tomllib.loads(text) == want
    assert "# the nut" in text
    assert "# kept" in text
    assert "inertia_kg_m2.value = 0.00015" in text


def test_sub_table_spelling_is_edited_in_place():
    base = 'name = "b"\n\n[nut.inertia_kg_m2]  # a table of its own\nvalue = 2.0e-4\nsource = "catalogue"\n'
    want = {"name": "b", "nut": {"inertia_kg_m2": {"value": 3e-4, "source": "fit"}}}
    text = document_toml(want, base)
    assert tomllib.loads(text) == want
    assert "# a table of its own" in text


def test_user_text_is_escaped_and_reads_back_exactly():
    p = _plant("paper-iprsm")
    text = p.to_toml(plant_file_path().read_text(encoding="utf-8"), name=HOSTILE, description=HOSTILE)
    for bad in ("\x1b", "\x07", "\r", "\u202e", "\x7f", "\x85"):
        assert bad not in text
    q = _load(text)
    assert q.name == HOSTILE
    assert q.description == HOSTILE
    fresh = p.to_toml(name=HOSTILE)
    assert "\x1b" not in fresh
    assert _load(fresh).name == HOSTILE


def test_header_lines_are_one_printable_comment_line_each():
    p = _plant("paper-iprsm")
    text = p.to_toml(plant_file_path().read_text(encoding="utf-8"), header=("not validated: " + HOSTILE, "second"))
    lines = text.splitlines()
    assert lines[0].startswith("# not validated: ev")
    assert "\\x1b" in lines[0]
    assert "\\n" in lines[0]
    assert lines[1] == "# second"
    assert _load(text).name == p.name


def test_lone_surrogate_refused_naming_the_key():
    p = _plant("paper-iprsm")
    with pytest.raises(ValueError, match=r"^name = .*lone surrogate U\+DCFF"):
        p.to_toml(plant_file_path().read_text(encoding="utf-8"), name="bad\udcff")
    with pytest.raises(ValueError, match=r"lone surrogate"):
        toml_string("\ud800")


def test_a_log_file_name_that_is_not_utf8_is_written_as_its_byte_in_sources_and_description():
    """A fit of a log named ``r<0xff>.csv`` (valid on Linux; Python's surrogateescape gives
    U+DCFF): its sources, [uncertainty] source and description name it. Was: ValueError (lone
    surrogate) when the file was composed, after the whole fit (prsa-fit: exit 3 "numerical
    failure: description = ...", no file)."""
    p = _plant("paper-iprsm")
    base = plant_file_path().read_text(encoding="utf-8")
    key = "nut.inertia_kg_m2"
    entry = {"dist": "normal", "sigma": 1.25e-6, "truncate": 1.959963984540054, "source": "fit: r\udcff.csv (95 % CI)"}
    fitted = Plant(p.name, p.values, {**p.sources, key: "fit: r\udcff.csv (95 % CI)"}, description=p.description,
                   uncertainty={**p.uncertainty, key: entry}, mechanism=p.mechanism, defaulted=p.defaulted)
    text = fitted.to_toml(base, name="fitted", keys=[key], uncertainty_keys=[key],
                          description="calibrated from r\udcff.csv and a\ud800")
    back = _load(text)
    assert back.sources[key] == "fit: r\\xff.csv (95 % CI)"
    assert back.uncertainty[key]["source"] == "fit: r\\xff.csv (95 % CI)"
    assert back.description == "calibrated from r\\xff.csv and a\\ud800"
    assert back.values[key] == p.values[key]
    assert back.name == "fitted"


def test_uncertainty_entries_replaced_removed_and_section_added():
    p = _plant("paper-iprsm")
    base = plant_file_path().read_text(encoding="utf-8")
    key = "nut.inertia_kg_m2"
    entry = {"dist": "normal", "sigma": 1.25e-6, "truncate": 1.959963984540054, "source": "fit: x"}
    unc = {k: v for k, v in p.uncertainty.items() if k != "friction.efficiency"}
    fitted = Plant(p.name, p.values, p.sources, description=p.description, uncertainty={**unc, key: entry},
                   mechanism=p.mechanism, defaulted=p.defaulted)
    text = fitted.to_toml(base, keys=[key], uncertainty_keys=[key, "friction.efficiency"])
    doc = tomllib.loads(text)
    assert doc["uncertainty"][key] == entry
    assert "friction.efficiency" not in doc["uncertainty"]
    # a base without [uncertainty]: the section is added, with its comment
    bare = 'name = "b"\n\n[nut]\ninertia_kg_m2 = { value = 2.0e-4, source = "c" }\n'
    want = {"name": "b", "nut": {"inertia_kg_m2": {"value": 2.0e-4, "source": "c"}}, "uncertainty": {key: entry}}
    text = document_toml(want, bare)
    assert tomllib.loads(text) == want
    assert "# What the fit leaves uncertain" in text


def test_numbers_keep_every_digit_and_their_type():
    doc = {"name": "n", "s": {"a": {"value": 0.1 + 0.2, "source": "x"}, "b": {"value": 3, "source": "y"},
                              "c": {"value": float("inf"), "source": "z"}, "d": {"value": 1e-300, "source": "w"}}}
    back = tomllib.loads(document_toml(doc))
    assert back == doc
    assert isinstance(back["s"]["b"]["value"], int)


def test_a_base_it_cannot_keep_is_written_afresh_with_a_note():
    # a table split around another one (valid TOML, "out of order"): the edit that removes a part
    # of it is refused by tomlkit 0.15 (IndexError) or gives another document; either way the
    # file written reads back as the document asked for
    base = 'name = "b"\n[nut.a]\nx = 1\n[other]\ny = 2\n[nut.b]\nz = 3\n'
    want = {"name": "b", "other": {"y": 2}, "nut": {"inertia_kg_m2": {"value": 2.0e-4, "source": "c"}}}
    assert tomllib.loads(document_toml(want, base)) == want


def test_an_edit_that_fails_falls_back_to_a_fresh_file(monkeypatch):
    import prsa_ctrl.plant.writer as W

    def broken(base_text, want):
        raise IndexError("tomlkit refused the edit")

    monkeypatch.setattr(W, "_edited", broken)
    want = {"name": "b", "nut": {"inertia_kg_m2": {"value": 2.0e-4, "source": "c"}}}
    text = document_toml(want, 'name = "b"  # the base\n')
    assert text.startswith(f"# {FRESH_NOTE}\n")
    assert tomllib.loads(text) == want

    monkeypatch.setattr(W, "_edited", lambda base_text, want: 'name = "wrong"\n')  # an edit that reads back wrong
    text = document_toml(want, 'name = "b"\n')
    assert text.startswith(f"# {FRESH_NOTE}\n")
    assert tomllib.loads(text) == want


def test_none_is_refused_naming_the_key():
    with pytest.raises(ValueError, match=r"^s\.k = None; expected"):
        document_toml({"name": "n", "s": {"k": None}})


def test_inline_value():
    assert inline_value({"a": [1, 2.5], "b": "q\""}) == '{ a = [1, 2.5], b = "q\\"" }'


def test_plant_toml_is_the_method():
    p = _plant("paper-iprsm")
    base = plant_file_path().read_text(encoding="utf-8")
    assert plant_toml(p, base, name="x") == p.to_toml(base, name="x")


def test_without_tomlkit_the_file_is_written_afresh_saying_why(monkeypatch):
    import sys

    from prsa_ctrl.plant.writer import NO_TOMLKIT_NOTE

    monkeypatch.setitem(sys.modules, "tomlkit", None)  # import tomlkit raises ImportError
    want = {"name": "b", "nut": {"inertia_kg_m2": {"value": 2.0e-4, "source": "c"}}}
    text = document_toml(want, 'name = "b"  # the base\n')
    assert text.startswith(f"# {NO_TOMLKIT_NOTE}\n")
    assert tomllib.loads(text) == want


# --- data files (drive exports): the same writer, strict values -------------------------------------

def test_data_lines_read_back_exactly_and_keys_stay_ascii():
    import tomllib

    from prsa_ctrl.plant.writer import data_lines

    doc = {"a": 1, "µ key": [0.1, 2.0, "\u202e"], "t": {"x y": True, "n": 2**70}, "arr": [{"k": "v"}, {"k": "w"}]}
    text = "\n".join(data_lines(doc)) + "\n"
    assert tomllib.loads(text) == doc
    assert text.isascii()


@pytest.mark.parametrize("value, message", [
    (float("nan"), "t.v = nan; expected a finite number (TOML export)"),
    (None, "t.v = None; expected a number, string, bool or list of those (TOML has no null)"),
    ([1.0, float("inf")], "t.v = inf; expected a finite number (TOML export)"),
])
def test_data_values_refuse_what_toml_cannot_hold(value, message):
    from prsa_ctrl.plant.writer import data_lines

    with pytest.raises(ValueError) as exc:
        data_lines({"t": {"v": value}})
    assert str(exc.value) == message


def test_the_export_writes_through_the_one_writer():
    from prsa_ctrl.io import export
    from prsa_ctrl.plant import writer

    d = {"format": "x", "speed": {"kp": 0.1, "name": "µ"}}
    assert export.dumps(d, "toml") == "# x (TOML)\n" + "\n".join(writer.data_lines(d)) + "\n"
    assert export.toml_value([1, "µ"]) == writer.data_value([1, "µ"])


def test_tomlkit_and_the_float_rule_live_in_the_writer_only():
    """One TOML writer: no other module imports tomlkit or formats a TOML float itself."""
    import ast
    from pathlib import Path

    import prsa_ctrl

    root = Path(prsa_ctrl.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel == "plant/writer.py":
            continue
        text = path.read_text(encoding="utf-8")
        for node in ast.walk(ast.parse(text)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "tomlkit" for n in names):
                found.append(f"{rel}: imports tomlkit")
        if 'for c in ".en"' in text or "for c in '.en'" in text:
            found.append(f"{rel}: a TOML float rule")
    assert found == []
