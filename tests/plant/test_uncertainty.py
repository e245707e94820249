"""[uncertainty] sections of plants and scenes; [spec] and [robust] scene sections."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from identification.test_fit import base, csv_files  # noqa: F401  (module fixtures: three toolkit logs)
from scipy import stats
from scipy.special import ndtr, ndtri

from prsa_ctrl import PlantFileError, SceneError
from prsa_ctrl.cli.fit import main as fit_main
from prsa_ctrl.plant import load_plant
from prsa_ctrl.plant.plantfile import Plant, builtin_plants, load_plant
from prsa_ctrl.plant.uncertainty import (CORRELATION_KEY, PSD_TOLERANCE, carry_correlation, correlation_entry, correlation_toml, parse_entries, uncertainty_model)
from prsa_ctrl.studies.scenesections import parse_scene_sections
from prsa_ctrl.studies.scene import load_scene, parse_scene

ROOT = Path(__file__).resolve().parents[2]
_DOC = tomllib.loads((ROOT / "plants" / "paper-iprsm.toml").read_text())
_SCENE = tomllib.loads((ROOT / "tuning" / "robust-load-step.toml").read_text())


def _plant_with(entries, origin="bad-plant.toml"):
    doc = copy.deepcopy(_DOC)
    doc["uncertainty"] = entries
    return Plant.from_dict(doc, origin=origin)


@pytest.mark.parametrize("name", builtin_plants())
def test_builtin_plants_document_their_uncertainty(name):
    p = load_plant(name)
    unc = uncertainty_model(p)
    assert len(unc) >= 2
    for e in unc.entries:
        assert e.source
        assert e.low <= e.nominal <= e.high
        assert e.source.split(":")[0] in ("paper", "assumption", "estimate", "fit") or e.source.startswith("paper")


def test_robust_scene_adds_its_uncertainty_to_the_plants():
    p, s = load_plant(), load_scene("robust-load-step")
    unc = uncertainty_model(p, s.sections.plant_overrides)
    e = {x.key: x for x in unc.entries}
    j = p.values["nut.inertia_kg_m2"]
    assert e["nut.inertia_kg_m2"].low == pytest.approx(0.5 * j)
    assert e["nut.inertia_kg_m2"].high == pytest.approx(1.5 * j)
    assert (e["drive.current_loop_bandwidth_hz"].low, e["drive.current_loop_bandwidth_hz"].high) == (500.0, 1500.0)
    assert s.sections.as_dict()["spec"]["peak_drop_rad_s"] > 0
    assert s.sections.as_dict()["spec"]["no_saturation"] is True


@given(seed=st.integers(0, 2**32), index=st.integers(0, 10**6))
@settings(max_examples=40)
def test_samples_stay_in_the_support_and_are_reproducible(seed, index):
    unc = uncertainty_model(load_plant(), load_scene("robust-load-step").sections.plant_overrides)
    a = unc.sample(np.random.default_rng([seed, index]))
    b = unc.sample(np.random.default_rng([seed, index]))
    assert a == b
    for e in unc.entries:
        assert e.low <= a[e.key] <= e.high


def test_distributions_have_the_stated_shape():
    p = _plant_with({
        "nut.inertia_kg_m2": {"dist": "uniform", "relative": 0.5, "source": "assumption: t"},
        "drive.current_loop_bandwidth_hz": {"dist": "loguniform", "low": 500.0, "high": 2000.0, "source": "assumption: t"},
        "friction.efficiency": {"dist": "normal", "sigma": 0.02, "truncate": 2.0, "source": "assumption: t"},
    })
    unc = uncertainty_model(p)
    rng = np.random.default_rng(3)
    xs = [unc.sample(rng) for _ in range(4000)]
    bw = np.log([x["drive.current_loop_bandwidth_hz"] for x in xs])
    # log-uniform: the log is uniform, so its median is the log-midpoint (1000 Hz)
    assert abs(np.median(bw) - math.log(1000.0)) < 0.05
    eta = np.array([x["friction.efficiency"] for x in xs])
    assert abs(eta.mean() - 0.85) < 0.002
    assert eta.min() >= 0.81
    assert eta.max() <= 0.89
    assert 0.015 < eta.std() < 0.02  # truncation at 2 sigma shrinks the std to 0.88 sigma
    assert len(unc.vertices()) == 8


_GOOD = {"dist": "uniform", "relative": 0.2, "source": "assumption: test"}

# (key, entry) pairs that must be rejected, each with a token the message must name.
_bad_entries = st.one_of(
    st.builds(lambda r: ("nut.inertia_kg_m2", {**_GOOD, "relative": r}),
              st.one_of(st.floats(max_value=-1e-9, allow_nan=False, allow_infinity=False), st.floats(min_value=1.0, max_value=1e6))),
    st.builds(lambda s: ("nut.inertia_kg_m2", {"dist": "normal", "sigma": s, "truncate": 3.0, "source": "a: b"}),
              st.floats(max_value=0.0, allow_nan=False, allow_infinity=False)),
    st.builds(lambda t: ("nut.inertia_kg_m2", {"dist": "normal", "relative_sigma": 0.1, "truncate": t, "source": "a: b"}),
              st.one_of(st.floats(max_value=0.0, allow_nan=False, allow_infinity=False), st.floats(min_value=6.001, max_value=1e9))),
    # normal that reaches non-positive inertia: nominal 2e-4, 3 sigma >= nominal
    st.builds(lambda s: ("nut.inertia_kg_m2", {"dist": "normal", "sigma": s, "truncate": 3.0, "source": "a: b"}),
              st.floats(min_value=0.7e-4, max_value=1.0)),
    st.builds(lambda lo: ("drive.current_loop_bandwidth_hz", {"dist": "loguniform", "low": lo, "high": 2000.0, "source": "a: b"}),
              st.floats(max_value=0.0, allow_nan=False, allow_infinity=False)),
    st.builds(lambda lo, hi: ("drive.current_loop_bandwidth_hz", {"dist": "uniform", "low": lo, "high": hi, "source": "a: b"}),
              st.floats(min_value=1001.0, max_value=1e5), st.floats(min_value=1.0, max_value=999.0)),
    # efficiency above 1 is not physical
    st.builds(lambda r: ("friction.efficiency", {**_GOOD, "relative": r}), st.floats(min_value=0.18, max_value=0.99)),
    st.builds(lambda d: ("nut.inertia_kg_m2", {**_GOOD, "dist": d}), st.text(min_size=0, max_size=8).filter(
        lambda d: d not in ("uniform", "normal", "loguniform"))),
    st.builds(lambda k: (k, dict(_GOOD)), st.sampled_from(["nut.mass_kg", "roller.count", "screw.starts", "foo.bar"])),
    st.builds(lambda s: ("nut.inertia_kg_m2", {**_GOOD, "source": s}), st.sampled_from(["", "   ", 3])),
    st.builds(lambda v: ("nut.inertia_kg_m2", {**_GOOD, "relative": v}), st.sampled_from([True, "0.2", float("nan"), float("inf")])),
    # static friction below dynamic at the low end of the support (a cross-check of the plant)
    st.builds(lambda r: ("friction.static", {**_GOOD, "relative": r}), st.floats(min_value=0.17, max_value=0.99)),
)


@given(_bad_entries)
@settings(max_examples=80)
def test_bad_plant_uncertainty_names_key_and_file(bad):
    key, entry = bad
    with pytest.raises(PlantFileError) as exc:
        _plant_with({key: entry})
    msg = str(exc.value)
    assert msg.startswith("bad-plant.toml: ")
    assert key in msg
    assert "\n" not in msg


@given(_bad_entries)
@settings(max_examples=40)
def test_bad_scene_uncertainty_names_key_and_file(bad):
    key, entry = bad
    doc = copy.deepcopy(_SCENE)
    doc["uncertainty"] = {key: entry}
    with pytest.raises(SceneError) as exc:
        s = parse_scene(doc, "bad-scene.toml")
        uncertainty_model(load_plant(), s.sections.plant_overrides)
    assert str(exc.value).startswith("bad-scene.toml: ")
    assert key in str(exc.value)


@pytest.mark.parametrize("section, key, value", [
    ("spec", "peak_drop_rad_s", -1.0),
    ("spec", "peak_drop_rad_s", "5"),
    ("spec", "ms", 0.9),
    ("spec", "no_saturation", 1),
    ("spec", "overshot", 1.0),
    ("robust", "aggregate", "median"),
    ("robust", "samples", -1),
    ("robust", "samples", 1.5),
    ("robust", "setpoints_rpm", []),
    ("robust", "final_loads_n", [-5.0]),
    ("robust", "monte_carlo", True),
    ("robust", "seedz", 1),
])
def test_bad_spec_or_robust_entry_names_key_and_file(section, key, value):
    doc = copy.deepcopy(_SCENE)
    doc[section][key] = value
    with pytest.raises(SceneError) as exc:
        parse_scene(doc, "bad-scene.toml")
    msg = str(exc.value)
    assert msg.startswith("bad-scene.toml: ")
    assert f"{section}.{key}" in msg


def test_a_spec_yield_without_a_bound_is_refused_naming_it():
    """``[spec] yield = 0.9`` alone: a target probability of meeting no bound. Was: accepted,
    then ``prsa-tune --design-to-spec`` said the scene "has no [spec] section"."""
    doc = copy.deepcopy(_SCENE)
    doc["spec"] = {"yield": 0.9}
    with pytest.raises(SceneError) as exc:
        parse_scene(doc, "bad-scene.toml")
    assert str(exc.value) == ("bad-scene.toml: spec.yield = 0.9 and no bound in [spec]; expected the bounds the "
                              "yield counts (e.g. spec.peak_drop_rad_s = 12.0)")
    doc["spec"] = {"yield": 0.9, "no_saturation": True}  # a bound, the yield counts it
    assert parse_scene(doc, "ok.toml") is not None


def test_scene_sections_round_trip():
    out = parse_scene_sections(_SCENE, "x.toml")
    assert set(out) == {"spec", "robust", "uncertainty"}
    assert out["robust"]["monte_carlo"] == 1000
    assert out["robust"]["aggregate"] == "worst"


def test_plants_without_uncertainty_still_load_and_overrides_keep_it():
    doc = copy.deepcopy(_DOC)
    doc.pop("uncertainty", None)
    p = Plant.from_dict(doc)
    assert len(uncertainty_model(p)) == 0
    q = load_plant().with_params({"nut.inertia_kg_m2": 3e-4})
    assert q.uncertainty == load_plant().uncertainty


# ------------------------------------------------------------------------------------------------
# Correlated uncertainty (issue 21): ``correlation`` in ``[uncertainty]``, its validation, the
# Gaussian-copula sampler, the unchanged uncorrelated path, scene overrides, and the writers'
# round trip.
#
# The references are written here with numpy/scipy only: each key's distribution is scipy's
# (uniform, log-uniform, truncated normal), the normal scores ``Phi^-1(F_i(x_i))`` of the draws
# must have the written correlation, and the uncorrelated draw is recomputed from the uniforms.
# ------------------------------------------------------------------------------------------------

PAPER = ROOT / "plants" / "paper-iprsm.toml"

J, BW, ETA, VISC, K = ("nut.inertia_kg_m2", "drive.current_loop_bandwidth_hz", "friction.efficiency",
                       "friction.viscous_n_m_s_per_rad", "contact.stiffness_n_per_mm_e")
ENTRIES = {
    J: {"dist": "uniform", "relative": 0.5, "source": "assumption: t"},
    BW: {"dist": "loguniform", "low": 500.0, "high": 2000.0, "source": "assumption: t"},
    ETA: {"dist": "normal", "sigma": 0.02, "truncate": 2.0, "source": "assumption: t"},
    VISC: {"dist": "normal", "relative_sigma": 0.2, "truncate": 1.959963984540054, "source": "assumption: t"},
    K: {"dist": "loguniform", "low": 5.0e4, "high": 2.0e5, "source": "assumption: t"},
}
BLOCK_KEYS = [J, BW, ETA, VISC]
R4 = [[1.0, -0.87, 0.3, 0.0], [-0.87, 1.0, -0.2, 0.1], [0.3, -0.2, 1.0, 0.5], [0.0, 0.1, 0.5, 1.0]]


def _plant(entries, origin="corr-plant.toml"):
    doc = copy.deepcopy(_DOC)
    doc["uncertainty"] = entries
    return Plant.from_dict(doc, origin=origin)


def _correlated(matrix=R4, keys=BLOCK_KEYS):
    return {**copy.deepcopy(ENTRIES), "correlation": {"keys": list(keys), "matrix": matrix, "source": "estimate: t"}}


def _reference_dist(e):
    """scipy's distribution of one resolved entry (independent of the toolkit's ppf)."""
    if e.dist == "uniform":
        return stats.uniform(e.low, e.high - e.low)
    if e.dist == "loguniform":
        return stats.loguniform(e.low, e.high)
    return stats.truncnorm((e.low - e.nominal) / e.sigma, (e.high - e.nominal) / e.sigma, loc=e.nominal, scale=e.sigma)


def _draws(model, n, seed):
    rng = np.random.default_rng(seed)
    xs = [model.sample(rng) for _ in range(n)]
    return {k: np.array([x[k] for x in xs]) for k in model.keys}


def test_copula_has_the_written_correlation_and_keeps_every_marginal():
    """5000 seeded draws: the normal scores have the matrix's correlation (Fisher standard error
    (1 - r^2)/sqrt(n), 5 of them), each marginal is scipy's distribution (KS test and mean within
    5 standard errors), nothing leaves its support, the key outside the block stays independent."""
    model = uncertainty_model(_plant(_correlated()))
    assert len(model.correlations) == 1
    assert model.correlations[0].keys == tuple(BLOCK_KEYS)
    n = 5000
    cols = _draws(model, n, 20261124)
    ents = {e.key: e for e in model.entries}
    scores = {}
    for k, x in cols.items():
        e, ref = ents[k], _reference_dist(ents[k])
        assert e.low <= x.min(), k
        assert x.max() <= e.high, k
        assert stats.kstest(x, ref.cdf).pvalue > 1e-4, k
        assert abs(x.mean() - ref.mean()) < 5 * ref.std() / math.sqrt(n), k
        scores[k] = stats.norm.ppf(np.clip(ref.cdf(x), 1e-15, 1 - 1e-15))
    order = [*BLOCK_KEYS, K]
    c = np.corrcoef(np.array([scores[k] for k in order]))
    want = np.eye(5)
    want[:4, :4] = R4
    assert np.all(np.abs(c - want) < 5 * (1 - want ** 2) / math.sqrt(n) + 1e-12), c


def _old_sample(model, rng):
    """The draw of the code before correlations existed: one uniform per key (sorted keys), each
    through its inverse CDF (formulas written out here)."""
    u = rng.random(len(model.entries))
    out = {}
    for e, ui in zip(model.entries, u):
        if e.dist == "uniform":
            out[e.key] = float(e.low + ui * (e.high - e.low))
        elif e.dist == "loguniform":
            out[e.key] = float(np.exp(math.log(e.low) + ui * (math.log(e.high) - math.log(e.low))))
        else:
            a, b = ndtr((e.low - e.nominal) / e.sigma), ndtr((e.high - e.nominal) / e.sigma)
            out[e.key] = float(np.clip(e.nominal + e.sigma * ndtri(a + ui * (b - a)), e.low, e.high))
    return out


@pytest.mark.parametrize("seed", [0, 1, 12345])
def test_without_correlation_every_draw_is_the_old_one_to_the_bit(seed):
    """No correlation: the same uniforms, the same values, bit for bit, and the generator left in
    the same state (what the Monte Carlo draws next, operating point and roller seed, unchanged).
    With a correlation, the keys outside its block are still drawn bit for bit as before."""
    plain = uncertainty_model(_plant(copy.deepcopy(ENTRIES)))
    corr = uncertainty_model(_plant(_correlated()))
    r1, r2, r3 = (np.random.default_rng(seed) for _ in range(3))
    for _ in range(50):
        new, old, c = plain.sample(r1), _old_sample(plain, r2), corr.sample(r3)
        assert new == old  # exact equality of floats
        assert c[K] == old[K]
        assert any(c[k] != old[k] for k in BLOCK_KEYS)
    assert r1.random() == r2.random() == r3.random()


def test_singular_correlation_is_accepted_and_drawn():
    """r = 1 (positive semi-definite, singular): the two keys move together exactly (equal
    normal scores); a 3 x 3 Gram matrix of three plane vectors (rank 2) samples with its
    correlation; an eigenvalue just below zero within the tolerance is accepted."""
    m = uncertainty_model(_plant(_correlated([[1.0, 1.0], [1.0, 1.0]], [ETA, VISC])))
    ents = {e.key: e for e in m.entries}
    cols = _draws(m, 500, 3)
    s1 = stats.norm.ppf(_reference_dist(ents[ETA]).cdf(cols[ETA]))
    s2 = stats.norm.ppf(_reference_dist(ents[VISC]).cdf(cols[VISC]))
    assert np.max(np.abs(s1 - s2)) < 1e-6
    gram = [[1.0, 0.5, -0.5], [0.5, 1.0, 0.5], [-0.5, 0.5, 1.0]]
    assert abs(np.linalg.eigvalsh(gram).min()) < 1e-12
    m3 = uncertainty_model(_plant(_correlated(gram, [J, ETA, VISC])))
    e3 = {e.key: e for e in m3.entries}
    n = 4000
    c3 = _draws(m3, n, 11)
    sc = np.array([stats.norm.ppf(np.clip(_reference_dist(e3[k]).cdf(c3[k]), 1e-15, 1 - 1e-15)) for k in (J, ETA, VISC)])
    g = np.array(gram)
    assert np.all(np.abs(np.corrcoef(sc) - g) < 5 * (1 - g ** 2) / math.sqrt(n) + 1e-6)
    # perturb along the null vector (1, -1, 1)/sqrt(3): eigenvalue -2 eps / 3
    for eps, ok in ((3e-10, True), (3e-9, False)):
        bad = [row[:] for row in gram]
        bad[0][2] = bad[2][0] = -0.5 - eps
        assert bool(np.linalg.eigvalsh(bad).min() >= -PSD_TOLERANCE) is ok
        if ok:
            uncertainty_model(_plant(_correlated(bad, [J, ETA, VISC])))
        else:
            with pytest.raises(Exception, match="eigenvalue"):
                _plant(_correlated(bad, [J, ETA, VISC]))


def test_vertices_stay_the_box_corners():
    plain, corr = (uncertainty_model(_plant(t)) for t in (copy.deepcopy(ENTRIES), _correlated()))
    assert corr.vertices() == plain.vertices()
    assert len(corr.vertices()) == 2 ** 5


_BASE_LINE = '"friction.viscous_n_m_s_per_rad" = { dist = "normal", relative_sigma = 0.2, truncate = 2.0, source = "estimate: t" }'
_PAIR = '["nut.inertia_kg_m2", "friction.efficiency"]'

#: (correlation line(s) appended to the paper plant's [uncertainty], a token the message must name)
BAD = [
    (f'correlation = {{ keys = ["nut.inertia_kg_m2", "drive.sample_time_s"], matrix = [[1.0, 0.5], [0.5, 1.0]], source = "e: t" }}',
     "'drive.sample_time_s' has no entry"),
    ('correlation = { keys = ["nut.inertia_kg_m2", "nut.inertia_kg_m2"], matrix = [[1.0, 0.5], [0.5, 1.0]], source = "e: t" }',
     "appears twice"),
    (f'correlation = [{{ keys = {_PAIR}, matrix = [[1.0, 0.5], [0.5, 1.0]], source = "e" }}, '
     '{ keys = ["friction.efficiency", "contact.stiffness_n_per_mm_e"], matrix = [[1.0, 0.1], [0.1, 1.0]], source = "e" }]',
     "in two blocks"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, 0.5]], source = "e: t" }}', "matrix = [[1.0, 0.5]]"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, 0.5], [0.4, 1.0]], source = "e: t" }}', "symmetric"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[0.9, 0.5], [0.5, 1.0]], source = "e: t" }}', "matrix[0][0] = 0.9"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, 1.5], [1.5, 1.0]], source = "e: t" }}', "matrix[0][1] = 1.5"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, nan], [nan, 1.0]], source = "e: t" }}', "nan"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, "0.5"], ["0.5", 1.0]], source = "e: t" }}', "'0.5'"),
    ('correlation = { keys = ["nut.inertia_kg_m2", "friction.efficiency", "drive.current_loop_bandwidth_hz"], '
     'matrix = [[1.0, 0.9, -0.9], [0.9, 1.0, 0.9], [-0.9, 0.9, 1.0]], source = "e: t" }', "eigenvalue"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, 0.5], [0.5, 1.0]] }}', "missing 'source'"),
    (f'correlation = {{ keys = {_PAIR}, source = "e: t" }}', "missing 'matrix'"),
    (f'correlation = {{ keys = {_PAIR}, matrix = [[1.0, 0.5], [0.5, 1.0]], source = "e", rho = 0.5 }}',
     "unknown field 'rho'"),
    ('correlation = { keys = ["nut.inertia_kg_m2"], matrix = [[1.0]], source = "e" }', "at least two"),
    ("correlation = []", "correlation = []"),
    ('correlation = "strong"', "correlation = 'strong'"),
]


@pytest.mark.parametrize("line,token", BAD, ids=[t for _, t in BAD])
def test_bad_correlation_is_refused_in_one_line_exit_2(line, token, tmp_path, capsys):
    from prsa_ctrl.cli.tune import main

    bad = tmp_path / "bad.toml"
    bad.write_text(PAPER.read_text() + _BASE_LINE + "\n" + line + "\n")
    code = main(["--plant", str(bad), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err, err
    assert str(bad) in lines[0], lines[0]
    assert "uncertainty.correlation" in lines[0], lines[0]
    assert token in lines[0], lines[0]


def test_a_good_correlation_line_loads(tmp_path):
    from prsa_ctrl.plant import load_plant

    good = tmp_path / "good.toml"
    good.write_text(PAPER.read_text() + _BASE_LINE + "\n"
                    + f'correlation = {{ keys = {_PAIR}, matrix = [[1, -0.87], [-0.87, 1]], source = "estimate: t" }}\n')
    m = uncertainty_model(load_plant(good))
    assert m.correlations[0].matrix == ((1.0, -0.87), (-0.87, 1.0))
    assert "correlation" in m.as_dict()[J]
    assert m.as_dict()[J]["correlation"]["with"] == {ETA: -0.87}


def test_scene_override_cuts_the_plants_block_and_names_the_keys():
    """The rule: a scene entry replaces the plant's; the plant's block keeps the keys whose entry
    is still the plant's (its principal sub-matrix), the cut keys named in the model's notes and
    in their as_dict; a scene's own block joins; plant_uncertainty = false drops the plant's."""
    plant = _plant(_correlated([[1.0, 0.3, -0.6], [0.3, 1.0, 0.2], [-0.6, 0.2, 1.0]], [J, ETA, K]))
    doc = copy.deepcopy(_SCENE)
    doc["robust"]["plant_uncertainty"] = True  # the scene overrides J and BW
    m = uncertainty_model(plant, parse_scene(doc, "scene.toml").sections.plant_overrides)
    assert [c.keys for c in m.correlations] == [(ETA, K)]
    assert m.correlations[0].matrix == ((1.0, 0.2), (0.2, 1.0))
    assert len(m.notes) == 1
    assert "'nut.inertia_kg_m2'" in m.notes[0]
    assert "scene.toml" in m.notes[0]
    d = m.as_dict()
    assert "correlation_note" in d[J]
    assert "correlation" not in d[J]
    assert d[ETA]["correlation"]["with"] == {K: 0.2}
    # the scene's own block over its own keys
    doc["uncertainty"]["correlation"] = {"keys": [J, BW], "matrix": [[1.0, -0.5], [-0.5, 1.0]], "source": "estimate: s"}
    m2 = uncertainty_model(plant, parse_scene(doc, "scene.toml").sections.plant_overrides)
    assert sorted(c.keys for c in m2.correlations) == sorted([(ETA, K), (J, BW)])
    cols = _draws(m2, 3000, 5)
    ents = {e.key: e for e in m2.entries}
    s = {k: stats.norm.ppf(np.clip(_reference_dist(ents[k]).cdf(cols[k]), 1e-15, 1 - 1e-15)) for k in (J, BW, ETA, K)}
    assert abs(np.corrcoef(s[J], s[BW])[0, 1] + 0.5) < 5 * 0.75 / math.sqrt(3000)
    assert abs(np.corrcoef(s[ETA], s[K])[0, 1] - 0.2) < 5 * 0.96 / math.sqrt(3000)
    assert abs(np.corrcoef(s[J], s[ETA])[0, 1]) < 5 / math.sqrt(3000)
    # the scene's uncertainty alone
    doc["robust"]["plant_uncertainty"] = False
    m3 = uncertainty_model(plant, parse_scene(doc, "scene.toml").sections.plant_overrides)
    assert [c.keys for c in m3.correlations] == [(J, BW)]
    assert not m3.notes


def test_parsed_table_parses_again_to_itself():
    e = parse_entries(_correlated(), "x.toml")
    assert parse_entries(e, "x.toml") == e
    assert e[CORRELATION_KEY][0]["keys"] == BLOCK_KEYS


def test_writers_round_trip_every_digit():
    """correlation_toml writes every digit: awkward floats read back exactly (TOML), from a
    covariance by correlation_entry (R = C / sqrt(C_ii C_jj), exactly symmetric, unit diagonal)."""
    rng = np.random.default_rng(9)
    a = rng.normal(size=(4, 7)) * np.array([1e-6, 3.0, 1e4, 0.2])[:, None]
    cov = a @ a.T
    blk = correlation_entry(BLOCK_KEYS, cov, "fit: t")
    sd = np.sqrt(np.diag(cov))
    assert np.allclose(np.array(blk["matrix"]), cov / np.outer(sd, sd), rtol=0, atol=1e-14)
    r = np.array(blk["matrix"])
    assert np.all(r == r.T)
    assert np.all(np.diag(r) == 1.0)
    for blocks in ([blk], [blk, {"keys": [K, "friction.static"], "matrix": [[1.0, 0.1 + 0.2], [0.1 + 0.2, 1.0]],
                                 "source": "estimate: \"quoted\" µ"}]):
        back = tomllib.loads("correlation = " + correlation_toml(blocks))["correlation"]
        assert (back if isinstance(back, list) else [back]) == blocks
    assert correlation_entry([J], [[1.0]], "s") is None
    assert correlation_entry([J, BW], [[1.0, 0.0], [0.0, 0.0]], "s") is None


def test_carry_correlation_keeps_blocks_of_unchanged_entries():
    base = _correlated([[1.0, 0.3, -0.6], [0.3, 1.0, 0.2], [-0.6, 0.2, 1.0]], [J, ETA, K])
    new = {k: v for k, v in base.items() if k != CORRELATION_KEY}
    new[J] = {"dist": "normal", "sigma": 1e-6, "truncate": 1.96, "source": "fit: x"}
    fit_block = {"keys": [J, BW], "matrix": [[1.0, 0.4], [0.4, 1.0]], "source": "fit: x"}
    out = carry_correlation(new, base, fit_block)
    assert out[CORRELATION_KEY] == [{"keys": [ETA, K], "matrix": [[1.0, 0.2], [0.2, 1.0]], "source": "estimate: t"},
                                    fit_block]
    assert CORRELATION_KEY not in carry_correlation(new, {k: v for k, v in base.items() if k != CORRELATION_KEY})


def test_models_with_and_without_correlation_differ_only_there():
    corr = uncertainty_model(_plant(_correlated()))
    plain = dataclasses.replace(corr, correlations=())
    assert plain == uncertainty_model(_plant(copy.deepcopy(ENTRIES)))


def test_carry_correlation_names_what_it_drops():
    base = _correlated([[1.0, 0.3, -0.6], [0.3, 1.0, 0.2], [-0.6, 0.2, 1.0]], [J, ETA, K])
    new = {k: v for k, v in base.items() if k != CORRELATION_KEY}
    new[J] = {"dist": "normal", "sigma": 1e-6, "truncate": 1.96, "source": "fit: x"}
    notes: list[str] = []
    carry_correlation(new, base, None, notes)
    assert notes == ["[uncertainty] correlation (estimate: t): dropped for nut.inertia_kg_m2 (its entry is no longer "
                     "the base's)"]


@given(seed=st.integers(0, 2**32 - 1), rank=st.integers(1, 4))
@settings(max_examples=25, deadline=None)
def test_any_valid_correlation_is_accepted_and_sampled_inside_the_supports(seed, rank):
    """Random correlations of any rank (Gram matrices of unit vectors, rounded to 12 digits as a
    user might type them): accepted, sampled inside every support, finite, reproducible."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(4, rank))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    g = np.round(v @ v.T, 12)
    np.fill_diagonal(g, 1.0)
    g = np.clip(0.5 * (g + g.T), -1, 1)
    model = uncertainty_model(_plant(_correlated(g.tolist())))
    ents = {e.key: e for e in model.entries}
    r1, r2 = np.random.default_rng(seed), np.random.default_rng(seed)
    for _ in range(20):
        a, b = model.sample(r1), model.sample(r2)
        assert a == b
        for k, x in a.items():
            assert math.isfinite(x)
            assert ents[k].low <= x <= ents[k].high


def test_carry_correlation_a_refit_block_replaces_the_base_block_over_its_keys():
    """A refit whose entries equal the base's (the same data refitted from its own fitted plant):
    the fit's block replaces the base's over those keys (was: both kept, the key in two blocks
    and the written file refused)."""
    base = _correlated([[1.0, 0.3, -0.6], [0.3, 1.0, 0.2], [-0.6, 0.2, 1.0]], [J, ETA, K])
    new = {k: v for k, v in base.items() if k != CORRELATION_KEY}  # every entry the base's own
    fit_block = {"keys": [J, ETA], "matrix": [[1.0, 0.25], [0.25, 1.0]], "source": "fit: x"}
    notes: list[str] = []
    out = carry_correlation(new, base, fit_block, notes)
    assert out[CORRELATION_KEY] == fit_block  # K alone is no block: nothing else is left
    assert notes == ["[uncertainty] correlation (estimate: t): dropped for nut.inertia_kg_m2, friction.efficiency "
                     "(the new correlation block holds them); nothing is left of the block"]
    parse_entries(out, "refit.toml")  # each key in one block: the file reader accepts it


@given(value=st.floats(1e-9, 1e6), ratio=st.floats(1e-3, 3.0), decimals=st.integers(0, 8))
@settings(max_examples=300, deadline=None)
def test_inner_truncation_never_crosses_the_bound(value, ratio, decimals):
    from prsa_ctrl.plant.uncertainty import inner_truncation

    sigma = value / ratio  # the bound 0 is `ratio` standard deviations below the value
    t = inner_truncation(value, sigma, 0.0, decimals=decimals)
    assert 0.0 <= t <= 1.959963984540054
    assert value - t * sigma >= 0.0
    if t < 1.959963984540054:
        assert t * 10**decimals == pytest.approx(round(t * 10**decimals), abs=1e-6)  # a multiple of 10^-decimals
        assert value - (t + 2 * 10.0**-decimals) * sigma < 0.0  # and the largest one (within a step)
    t_open = inner_truncation(value, sigma, 0.0, open_floor=True, decimals=decimals)
    assert t_open == 0.0 or value - t_open * sigma > 0.0


def test_inner_truncation_rounds_inward_where_rounding_to_nearest_crossed():
    from prsa_ctrl.plant.uncertainty import inner_truncation

    value, sigma = 1.2345679, 1.0
    assert value - round(value / sigma * (1 - 1e-9), 6) * sigma < 0  # the old rule: past the bound
    t = inner_truncation(value, sigma, 0.0)
    assert t == 1.234567
    assert value - t * sigma >= 0
    assert inner_truncation(0.9, 0.1, 0.0, 1.0) == 1.0  # the upper bound of a fraction too
    assert inner_truncation(5.0, 1.0, 0.0) == 1.959963984540054  # the 95 % limit when it fits
    with pytest.raises(ValueError, match="sigma > 0"):
        inner_truncation(1.0, 0.0, 0.0)


# ------------------------------------------------------------------------------------------------
# The rotary fit writes its correlation (issue 21): ``prsa-fit --uncertainty-from-fit`` on
# three logs of a perturbed paper plant writes, in the fitted plant's ``[uncertainty]``, the
# correlation of the keys written with the fit's own entry, computed here from the covariance in
# the fit's JSON report (numpy); the file reads back to the same numbers; the default mode (the
# base's entries kept, no fit entry for a key the base left without one) writes none but keeps
# the base's own correlation where its keys' entries are unchanged.
# ------------------------------------------------------------------------------------------------

def test_rotary_fit_writes_the_covariance_correlation(csv_files, tmp_path):  # noqa: F811
    _, paths = csv_files
    out, rep = tmp_path / "fitted.toml", tmp_path / "fit.json"
    assert fit_main([*paths, "--out", str(out), "--json", str(rep), "--uncertainty-from-fit"]) == 0
    report = json.loads(rep.read_text())
    doc = tomllib.loads(out.read_text())
    corr = doc["uncertainty"]["correlation"]
    cov = report["covariance"]
    fitted = [k for k, v in report["parameters"].items() if not v["kept_base"] and k in doc["uncertainty"]
              and doc["uncertainty"][k]["source"].startswith("fit: ")]
    assert corr["keys"] == fitted
    assert len(fitted) >= 4
    idx = [cov["keys"].index(k) for k in fitted]
    c = np.array(cov["matrix"])[np.ix_(idx, idx)]
    sd = np.sqrt(np.diag(c))
    assert np.max(np.abs(np.array(corr["matrix"]) - c / np.outer(sd, sd))) < 1e-12
    plant = load_plant(out)
    assert plant.uncertainty["correlation"] == corr  # read back to every digit
    m = uncertainty_model(plant)
    assert [c.keys for c in m.correlations] == [tuple(fitted)]


def test_default_mode_keeps_the_bases_correlation(csv_files, tmp_path):  # noqa: F811
    """The paper base with a correlation between two keys the fit does not touch
    (contact stiffness and roller position error): kept as it is; between a fitted key (its
    entry replaced by the fit's) and an untouched one: dropped with it."""
    _, paths = csv_files
    keep = ('correlation = { keys = ["contact.stiffness_n_per_mm_e", "tolerance.roller_position_std_um"], '
            'matrix = [[1.0, 0.25], [0.25, 1.0]], source = "estimate: test" }\n')
    base_file = tmp_path / "base.toml"
    base_file.write_text(PAPER.read_text() + keep)
    out = tmp_path / "fitted.toml"
    assert fit_main([*paths, "--plant", str(base_file), "--out", str(out)]) == 0
    got = tomllib.loads(out.read_text())["uncertainty"]["correlation"]
    assert got == {"keys": ["contact.stiffness_n_per_mm_e", "tolerance.roller_position_std_um"],
                   "matrix": [[1.0, 0.25], [0.25, 1.0]], "source": "estimate: test"}
    cut = ('correlation = { keys = ["nut.inertia_kg_m2", "contact.stiffness_n_per_mm_e"], '
           'matrix = [[1.0, 0.25], [0.25, 1.0]], source = "estimate: test" }\n')
    base_file.write_text(PAPER.read_text().replace(
        '"nut.inertia_kg_m2" = { dist = "uniform", relative = 0.3,', '"nut.inertia_kg_m2" = { dist = "uniform", low = 1.9e-4, high = 2.1e-4,')
        + cut)
    out2, rep2 = tmp_path / "fitted2.toml", tmp_path / "fit2.json"
    assert fit_main([*paths, "--plant", str(base_file), "--out", str(out2), "--json", str(rep2)]) == 0
    assert any("correlation (estimate: test): dropped for nut.inertia_kg_m2 (its entry is no longer" in w
               for w in json.loads(rep2.read_text())["warnings"])
    unc2 = tomllib.loads(out2.read_text())["uncertainty"]
    assert unc2["nut.inertia_kg_m2"]["source"].startswith("fit: ")  # excludes the fitted value: replaced
    assert "correlation" not in unc2
    load_plant(out2)
