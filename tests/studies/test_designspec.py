"""Design to the spec: proposals from the linear scenario models, chosen by the nonlinear Monte
Carlo on common samples, reported on fresh ones (issue 34)."""

import numpy as np
import pytest

from prsa_ctrl.drive.pid import PID
from prsa_ctrl.plant.plantfile import load_plant
from prsa_ctrl.studies.scene import load_scene
from spec_scenes import ROLLER_SPEC_SCENE, check_rule as _check_rule


@pytest.fixture(scope="module")
def roller(tmp_path_factory):
    path = tmp_path_factory.mktemp("designspec") / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    return load_plant("rollerscrew-30x5"), load_scene(str(path))


def test_design_to_spec_chooses_by_the_rule_and_reports_fresh_samples(roller):
    from prsa_ctrl.plant.uncertainty import uncertainty_model
    from prsa_ctrl.studies.designspec import design_to_spec
    from prsa_ctrl.studies.montecarlo import draw_sample, run_monte_carlo
    from prsa_ctrl.studies.scenerobust import operating_points

    plant, scene = roller
    extra = {"rule of thumb": PID(0.6361989083357843, 79.94711266598183)}
    r = design_to_spec(plant, scene, n_search=4, n_final=4, seed=3, ms_levels=(1.4, 1.5), extra=extra)
    # nominal and robust at two Ms bounds, plus the given design (unless a duplicate)
    assert set(r.designs) >= {"rule of thumb"} and len(r.designs) >= 3
    names = {row["name"] for row in r.search["rows"]}
    assert names == set(r.designs)
    if r.chosen is None:
        assert all(row["passed"] == 0 for row in r.search["rows"]) and r.final is None
        return
    _check_rule({**r.search, "table": r.search["rows"], "name": r.chosen, "design": r.chosen})
    # the reported yield is an independent Monte Carlo's of the chosen gains on seed + 1 ...
    ref = run_monte_carlo(plant, scene, {"x": r.pid}, 4, seed=4, workers=1, quiet=True).designs[0]
    fy = r.final_yield
    assert (fy.passed, fy.n, fy.ci95) == (ref.passed, ref.n, ref.ci95) and r.final_seed == 4
    # ... whose samples are not the search's
    unc, ops = uncertainty_model(plant, scene), tuple(operating_points(scene))
    for i in range(4):
        assert draw_sample(unc, ops, 3, i)[0] != draw_sample(unc, ops, 4, i)[0]
    text = r.format("iae")
    assert f"* {r.chosen}" in text and "fresh samples (seed 4, not used by the search)" in text


@pytest.mark.parametrize("kw, match", [({"n_search": 0}, "n_search = 0"), ({"n_final": True}, "n_final = True"),
                                       ({"seed": -1}, "seed = -1"), ({"ms_levels": (1.0,)}, "ms_levels"),
                                       ({"ms_levels": (float("nan"),)}, "ms_levels")])
def test_design_to_spec_bad_arguments_are_named_before_any_work(roller, kw, match):
    from prsa_ctrl.studies.designspec import design_to_spec

    with pytest.raises(ValueError, match=match):
        design_to_spec(*roller, **kw)


@pytest.mark.parametrize("argv, match", [
    (["--scene", "paper-load-step", "--design-to-spec"], "has no [spec] section"),
    (["--scene", "robust-load-step", "--design-to-spec", "--monte-carlo", "0"], "--monte-carlo 0"),
    (["--scene", "paper-move", "--design-to-spec"], "--design-to-spec does not apply to a move scene"),
])
def test_cli_design_to_spec_refusals_are_one_line_exit_2(argv, match, capsys):
    from prsa_ctrl.cli.tune import main as tune_main

    code = tune_main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and match in err[0], err


@pytest.mark.slow
def test_cli_design_to_spec_exports_the_chosen_design(roller, tmp_path, capsys):
    """``prsa-tune --design-to-spec`` on the roller-screw scene, 8 final samples: the JSON's
    recommendation is the search's choice with the fresh samples' yield, the export holds it."""
    import json
    import tomllib

    from prsa_ctrl.cli.tune import main as tune_main

    path = tmp_path / "rollerscrew-spec.toml"
    path.write_text(ROLLER_SPEC_SCENE, encoding="utf-8")
    out, exp = tmp_path / "r.json", tmp_path / "drive.toml"
    code = tune_main(["--plant", "rollerscrew-30x5", "--scene", str(path), "--design-to-spec", "--monte-carlo", "8",
                      "--workers", "2", "--json", str(out), "--export", str(exp)])
    text = capsys.readouterr().out
    assert code == 0, text
    d = json.loads(out.read_text())
    dts, rec = d["design_to_spec"], d["recommended"]
    assert rec["name"] == dts["chosen"] and rec["passed"] == dts["passed"] and rec["samples"] == 8
    assert dts["final_seed"] != dts["search_seed"]
    assert [x["name"] for x in d["monte_carlo"]["designs"]] == [dts["chosen"]]
    _check_rule({**dts["search"], "table": dts["search"]["rows"], "name": dts["chosen"], "design": dts["chosen"]})
    t = tomllib.loads(exp.read_text())
    assert t["design"]["name"] == dts["chosen"]
    assert t["speed_controller"]["continuous"]["kp_n_m_s_per_rad"] == dts["gains"]["kp"]
