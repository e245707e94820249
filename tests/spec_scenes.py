"""Shared by the design-to-the-spec tests (issue 34): the roller-screw scenes, a ball-screw
scene and an independent check of the recommendation rule on a table's own numbers.

Why the issue's table (rule of thumb 97.5 %) is not that of ``ROLLER_SPEC_SCENE`` on the built-in
``rollerscrew-30x5`` (rule of thumb 13.5 %, 27/200; measured 2026-11-27):

- The rule of thumb is one fixed design, computed once on the *nominal* plant
  (:func:`prsa_ctrl.studies.paper.default_pid`: crossover 2 pi 1000 Hz / 10 with the nominal
  reflected inertia 1.0125e-3 kg m^2: kp 0.636 N m s/rad, ki 79.9 N m/rad), not per sample. On
  the built-in plant's 4 kHz speed loop (250 us sample, one sample of computation delay, 0.2 ms
  speed filter) its Ms is 1.669 on the nominal plant itself and 2.5..2.9 at the light-inertia
  corners, so it fails ``Ms <= 1.5`` on most samples whatever the load step. The same gains on
  a 16 kHz speed loop (62.5 us: ``ROLLER_16K_PLANT``) have Ms p50 1.32 and reach 90..92.5 %.
- Recovery is measured as the error back inside 5 % of the peak drop for good
  (:data:`prsa_ctrl.sim.metrics.DEFAULT_BAND`). By that measure the rule of thumb recovers in
  37 ms (16 kHz) to 43 ms (4 kHz) on the nominal plant; "back inside 2 % of the setpoint"
  gives 18..34 ms. No PI meets 30 ms on most samples by our measure: the best linear yield of
  a 15 x 15 kp x ki grid with ``recovery_time_s = 0.03`` is 5 % (4 kHz) and 20 % (continuous
  controller). The scenes state 50 ms (the rule of thumb's p95 is 37 ms at 16 kHz).
- The rest of the issue's table matches the 4 kHz run within its intervals (nominal 66.0 %
  against 67.5 %, PM 60 deg 89.0 % against 86.5 %, the robust design at Ms 1.4 failing on the
  peak drop), so the plant and the load step are most likely the issue's: 1000 -> 5000 N, a
  pressing actuator's tool meeting the part, 40 % of the axis's rated 10 kN.
"""

#: A 30 mm roller-screw actuator as in issue 34: inertia +-50 %, current loop 500..1200 Hz,
#: efficiency 0.82 +- 0.03, two setpoints; spec peak drop <= 12 rad/s, Ms <= 1.5, no saturation;
#: recovery 50 ms (see the module docstring: 30 ms is out of reach of every PI by our measure).
ROLLER_SPEC_SCENE = '''
name = "rollerscrew-spec"

[operating]
setpoint_rpm = 300.0
initial_load_n = 1000.0
final_loads_n = [5000.0]
step_time_s = 0.05
duration_s = 0.15

[tuning]
objective = "iae"
controller = "pi"
ms_max = 1.4
candidates = 2

[verify]
fidelity = "auto"
discrete = true

[uncertainty]
"axis.motor_inertia_kg_m2" = { dist = "uniform", relative = 0.5, source = "assumption: attached rotating load" }
"drive.current_loop_bandwidth_hz" = { dist = "loguniform", low = 500.0, high = 1200.0, source = "assumption: drives" }
"friction.efficiency" = { dist = "uniform", low = 0.79, high = 0.85, source = "assumption: 0.82 +- 0.03" }

[spec]
peak_drop_rad_s = 12.0
recovery_time_s = 0.05
ms = 1.5
no_saturation = true
yield = 0.95

[robust]
aggregate = "worst"
plant_uncertainty = false
setpoints_rpm = [300.0, 600.0]
final_loads_n = [5000.0]
vertices = true
samples = 0
seed = 1
monte_carlo = 200
'''


def roller_16k_plant() -> str:
    """The built-in ``rollerscrew-30x5`` on a 16 kHz speed loop: the plant file's text with only
    its sample time (and name) changed, everything else as built in."""
    from prsa_ctrl.plant.plantfile import plant_file_path

    text = plant_file_path("rollerscrew-30x5").read_text("utf-8")
    old = 'sample_time_s = { value = 2.5e-4, source = "assumption: 4 kHz speed loop of a servo drive" }'
    assert old in text
    assert 'name = "rollerscrew-30x5"' in text
    return text.replace(old, 'sample_time_s = { value = 6.25e-5, source = "assumption: 16 kHz speed loop of a '
                             'current servo drive (62.5 us)" }').replace('name = "rollerscrew-30x5"',
                                                                         'name = "rollerscrew-30x5-16k"')


#: A machine-tool feed axis (built-in ``ballscrew-32x10``, 8 kHz speed loop): an end mill entering
#: the cut raises the feed force from 500 N to 3000 N at 3 and 5 m/min (300, 500 rpm at 10 mm
#: lead). The plant's own uncertainty (stroke position 50..950 mm, table mass +-30 %) plus the
#: drive's current loop (2 kHz +- 25 %) and the screw's efficiency (0.9 +- 0.03). Spec: the feed
#: dips by at most 20 % of the slower feed (6.28 rad/s), recovers in 30 ms (the issue's), Ms <=
#: 1.5 (the issue's). Stated first at 10 % (3.14 rad/s): no PI of a 15 x 15 grid (kp 0.2..2 x,
#: ki/kp 0.2..5 x the rule of thumb's) met that together with Ms <= 1.5 on any of 40 samples'
#: linear models (each bound alone is met on all), so 20 %. The rule of thumb (crossover 200 Hz)
#: breaks Ms <= 1.5 on every one of those samples.
BALL_CUT_SCENE = '''
name = "ballscrew-cut-spec"

[operating]
setpoint_rpm = 300.0
initial_load_n = 500.0
final_loads_n = [3000.0]
step_time_s = 0.05
duration_s = 0.15

[tuning]
objective = "iae"
controller = "pi"
ms_max = 1.4

[verify]
fidelity = "auto"
discrete = true

[uncertainty]
"drive.current_loop_bandwidth_hz" = { dist = "uniform", low = 1500.0, high = 2500.0, source = "assumption: drives of one family, 2 kHz +- 25 %" }
"friction.efficiency" = { dist = "uniform", low = 0.87, high = 0.93, source = "assumption: ball-screw efficiency 0.9 +- 0.03" }

[spec]
peak_drop_rad_s = 6.28
recovery_time_s = 0.03
ms = 1.5
no_saturation = true
yield = 0.95

[robust]
aggregate = "worst"
plant_uncertainty = true
setpoints_rpm = [300.0, 500.0]
final_loads_n = [3000.0]
vertices = true
samples = 0
seed = 1
monte_carlo = 200
'''


def check_rule(rec):
    """Independent check of the rule on the table's own numbers: the recommended yield is below
    no other by more than the two Wilson 95 % half-widths added."""
    from prsa_ctrl.studies.montecarlo import wilson_interval

    rows = {r["name"]: r for r in rec["table"]}
    if rec["name"] is None:  # none recommended: only when no design meets the spec on any sample
        assert all(r["passed"] == 0 for r in rows.values())
        assert rec["design"] is None
        return
    me = rows[rec["name"]]
    h = lambda r: (lambda lo, hi: (hi - lo) / 2)(*wilson_interval(r["passed"], r["samples"]))  # noqa: E731
    for r in rows.values():
        assert r["passed"] / r["samples"] - me["passed"] / me["samples"] <= h(r) + h(me) + 1e-12, (r, me)


