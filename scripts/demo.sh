#!/usr/bin/env bash
# The main job: installs what it needs, then finds a 7-piece interlocking 4x4x4 cube, verifies it and
# writes it (assembly.json, assembly.puz, assembly.png) under out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
.venv/bin/rllock solve --shape cube4 --pieces 7 --count 1 --seed 0 --out out/demo
.venv/bin/rllock verify out/demo/assembly_001/assembly.json
