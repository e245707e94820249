#!/usr/bin/env bash
# The README's test command: a fresh virtual environment with the newest releases of every
# dependency (as a newcomer gets them today), then the whole test suite.
#   bash scripts/fresh-test.sh [pytest arguments]
# The environment lives outside the checkout (PRSA_TEST_VENV, default: a folder in $TMPDIR) and
# is rebuilt from scratch at every run, so packages installed earlier cannot mask a new release.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${PRSA_TEST_VENV:-${TMPDIR:-/tmp}/prsa-ctrl-test-venv}"
python3 -m venv --clear "$venv"
# setuptools reuses build/ when its files look newer than the sources (a copied tree): start clean.
rm -rf build ./*.egg-info
"$venv/bin/python" -m pip install --quiet --upgrade pip
"$venv/bin/python" -m pip install --quiet --upgrade --upgrade-strategy eager ".[test,notebooks,dask,app]" "playwright>=1.40"
# The browser tests (tests/app/test_app_browser.py) drive Debian's Chromium (Playwright's own browser
# download cannot work here): install it where missing and possible; without it they skip with
# one line, and under CI=true they fail.
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing Debian's chromium for the browser tests"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } >/dev/null \
      || echo "could not install chromium: the browser tests will skip (fail under CI=true)"
  else
    echo "no chromium and no root apt-get: the browser tests will skip (fail under CI=true)"
  fi
fi
echo "fresh environment $venv:"
"$venv/bin/python" -m pip list --format=freeze 2>/dev/null \
  | grep -iE '^(numpy|scipy|casadi|control|matplotlib|filterpy|dask|distributed|pytest|hypothesis|bokeh|playwright)==' \
  | tr '\n' ' '
echo
export MPLBACKEND=Agg
# The tests import the installed (non-editable) package, so a file missing from the package data
# fails here as it would for a user (`python -m pytest` would put the checkout first on sys.path).
"$venv/bin/pytest" -q "$@"
