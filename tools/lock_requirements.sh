#!/usr/bin/env bash
# Regenerate requirements/lock.txt, the constraints of every pip step of tools/bootstrap.sh.
#
# Resolves build.txt, ros.txt and base.txt afresh (a dry run in a scratch venv: nothing is
# installed, and the old lock is not applied) and pins every package pip would take from
# PyPI. Run it after changing one of those files, then `make test` before committing.
#
#   tools/lock_requirements.sh             # with python3
#   PYTHON=python3.11 tools/lock_requirements.sh
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

"${PYTHON:-python3}" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --disable-pip-version-check --no-input -q \
  --dry-run --ignore-installed --report "$tmp/report.json" \
  -r requirements/build.txt -r requirements/ros.txt -r requirements/base.txt
"$tmp/venv/bin/python" - "$tmp/report.json" requirements/lock.txt <<'PY'
import json
import sys

report, out = sys.argv[1], sys.argv[2]
with open(report) as f:
    pins = sorted({f"{it['metadata']['name']}=={it['metadata']['version']}"
                   for it in json.load(f)["install"]}, key=str.lower)
header = """\
# Every package the venv installs from PyPI, at the version the tests last passed with:
# the constraints (-c) of each pip step of tools/bootstrap.sh, so that a fresh machine gets
# the same transitive dependencies as CI, not their newest releases.  The top-level choices
# stay in build.txt, ros.txt and base.txt; this file only fixes what they pull in.
# Regenerate after changing those files: tools/lock_requirements.sh.
"""
with open(out, "w") as f:
    f.write(header + "\n".join(pins) + "\n")
print(f"lock_requirements: {len(pins)} packages -> {out}")
PY
