#!/usr/bin/env bash
# Regenerate the README's two pictures (docs/img/) with the package's own commands:
#   docs/img/closed_loop.png   cwfs-ros demo --check      (its closed_loop.png)
#   docs/img/pair_demo.png     cwfs-ros pair-demo         (its demo_estimate.png)
# Both with their default arguments (seeds fixed), so a rerun on the same code gives the same
# loop and pair. The PNGs are reduced to a 256-colour palette to keep the repository small.
# Usage: tools/make_readme_figures.sh   (from the repository root, after `make venv`)
set -euo pipefail
cd "$(dirname "$0")/.."
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
.venv/bin/cwfs-ros demo --check --out "$out/demo"
.venv/bin/cwfs-ros pair-demo --out "$out/pair"
mkdir -p docs/img
.venv/bin/python - "$out" <<'PY'
import sys
from pathlib import Path

from PIL import Image

out = Path(sys.argv[1])
for src, dst in [(out / "demo" / "closed_loop.png", "docs/img/closed_loop.png"),
                 (out / "pair" / "demo_estimate.png", "docs/img/pair_demo.png")]:
    Image.open(src).convert("RGB").quantize(256).save(dst, optimize=True)
    print(f"{dst}: {Path(dst).stat().st_size // 1024} kB from {src.name}")
PY
