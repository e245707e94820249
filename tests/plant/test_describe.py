"""prsa_ctrl.plant.describe: ``used_keys`` and ``describe_plant`` (``prsa-tune --show-plant``)
list only the keys a plant's mechanism uses (issue 33, "seen by a newcomer").

The oracle is independent of the trace in :func:`prsa_ctrl.plant.describe.keys_read`: each key is
changed through the public ``Plant.with_params`` (validated, defaults re-derived) and the
public ``plant_model`` of every fidelity is compared at this file's own states."""

import warnings

import numpy as np
import pytest

from prsa_ctrl.plant import describe_plant, load_plant, plant_model
from prsa_ctrl.plant.describe import used_keys
from prsa_ctrl.plant.schema import KIND, LOOP_KEYS, NON_NEGATIVE_INTEGER, POSITIVE_INTEGER
from prsa_ctrl.errors import PlantFileError

PLANTS = {"inverted-roller-screw": "paper-iprsm", "roller-screw": "rollerscrew-30x5",
          "ball-screw": "ballscrew-32x10", "linear-axis": "examples/emps/plant.toml"}
ROLLER_ONLY = ("roller.", "cage.", "contact.", "thread.", "tolerance.")


def _load(mechanism):
    import pathlib

    name = PLANTS[mechanism]
    if "/" in name:
        name = pathlib.Path(__file__).resolve().parents[2] / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_plant(name)


def _outputs(plant):
    """f, h and power of every fidelity at seeded states sweeping the motor speed 0, +-1e-7 ...
    1e2 rad/s (stick band, Stribeck range, running), both load directions."""
    fids = ("rigid", "compliant") + (("multi-roller",) if plant.mechanism == "inverted-roller-screw" else ())
    out = []
    for fid in fids:
        m = plant_model(plant, fid)
        rng = np.random.default_rng(7)
        for w in [0.0] + [s * 10.0 ** (k / 8.0) for k in range(-56, 17) for s in (1, -1)]:
            x = [w if n == "omega_nut" else {"x_roller": 3e-5, "delta_screw": 3e-5, "v_roller": 2e-3, "v_screw": 2e-3,
                                             "omega_cage": 20.0, "tau_motor": 1.0}.get(n, 1.0) * rng.uniform(-1, 1)
                 for n in m.state_names]
            u = [rng.uniform(-2, 2), rng.uniform(-3000, 3000)]
            out += [np.asarray(f(x, u), float).ravel() for f in (m.f, m.h, m.power)]
    return np.concatenate(out)


def _changed(plant, key):
    """``plant`` with ``key`` changed through ``with_params`` (25 % up or down, +-1 for an
    integer, 2 % if the geometry refuses 25 %, a small value for a zero), or None where the plant refuses every change."""
    v = plant.values[key]
    integer = KIND[key] in (POSITIVE_INTEGER, NON_NEGATIVE_INTEGER)
    tries = (v + 1, v - 1) if integer else ((1.25 * v, 0.8 * v, 1.02 * v, 0.98 * v) if v else (1e-6, 1e-4, 1e-3, 1e-2, 1e-1))
    for new in tries:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return plant.with_params({key: int(new) if integer else new})
        except PlantFileError:
            continue
    if key in ("screw.lead_mm", "nut.lead_mm"):  # the inverted design: equal leads, meshing pitches
        joint = {f"{p}.{k}": 2 * plant.values[f"{p}.{k}"] for p in ("screw", "nut") for k in ("lead_mm", "starts")}
        try:
            return plant.with_params({k: int(x) if k.endswith("starts") else x for k, x in joint.items()})
        except PlantFileError:
            pass
    return None


@pytest.fixture(scope="module", params=list(PLANTS))
def case(request):
    plant = _load(request.param)
    return plant, used_keys(plant), _outputs(plant)


def test_every_listed_key_changes_the_model_or_is_documented_as_used(case):
    plant, used, ref = case
    unexplained = []
    for key in used:
        if key in LOOP_KEYS or plant.sources[key].startswith("derived"):
            continue  # documented: the sampled loop's key (LOOP_KEYS) / derived from given keys (DEFAULTS)
        other = _changed(plant, key)
        assert other is not None, key
        loop_moved = any(other.values[k] != plant.values[k] for k in LOOP_KEYS if k in plant.values)
        if not loop_moved and np.array_equal(_outputs(other), ref):
            unexplained.append(key)
    assert unexplained == []


def test_every_key_left_out_changes_nothing(case):
    plant, used, ref = case
    left_out = [k for k in plant.values if k not in used and not plant.sources[k].startswith("derived")]
    assert left_out  # every mechanism leaves some out (unused starts at least)
    for key in left_out:
        other = _changed(plant, key)
        if other is None:
            continue
        out = _outputs(other)
        scale = np.maximum(np.abs(ref), 1e-12 * np.max(np.abs(ref)))
        assert np.all(np.abs(out - ref) <= 1e-9 * scale), key
        assert all(other.values[k] == plant.values[k] for k in used), key  # nothing used derives from it


def test_ball_screw_lists_no_roller_screw_keys():
    plant = _load("ball-screw")
    text = describe_plant(plant)
    rows = [ln.strip() for ln in text.splitlines() if ln.startswith("  ")]
    assert not [r for r in rows if r.startswith(ROLLER_ONLY)]
    assert "roller.count" not in text
    assert "[cage]" not in text
    assert "[contact]" not in text
    assert [k for k in used_keys(plant) if k.startswith(ROLLER_ONLY)] == []


def test_inverted_roller_screw_lists_its_rollers_and_contacts():
    text = describe_plant(_load("inverted-roller-screw"))
    for key in ("roller.count", "cage.inertia_kg_m2", "contact.stiffness_n_per_mm_e", "tolerance.roller_runout_um"):
        assert f"  {key} " in text


def test_a_given_key_the_mechanism_does_not_use_is_named(tmp_path):
    from prsa_ctrl.plant.plantfile import plant_file_path

    text = plant_file_path("ballscrew-32x10").read_text(encoding="utf-8")
    text = text.replace("[drive]", '[roller]\ncount = { value = 7, source = "typed by hand" }\n[drive]', 1)
    path = tmp_path / "ball.toml"
    path.write_text(text, encoding="utf-8")
    shown = describe_plant(load_plant(path)).splitlines()
    assert shown[-1] == "given but not used by the ball-screw model: roller.count"
    assert not any(ln.strip().startswith("roller.count") for ln in shown[:-1])
