"""Tests of prsa_ctrl.cli (a package, so that tests/cli/test_fit.py and tests/identification/test_fit.py,
named after modules of the same name in two packages, import under distinct names)."""
