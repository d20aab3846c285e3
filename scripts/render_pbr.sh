#!/usr/bin/env bash
# Render a physically based frame set (issue 28) one scene per CPU slot, so that other jobs (and
# `cpu --quiet` timings) get the machine between scenes; cached scenes are skipped in no time.
#   bash scripts/render_pbr.sh tuning "clean=20 OR=20 clutter=20"
#   bash scripts/render_pbr.sh held_out "clean=20 OR=20 clutter=20"
#   RENDER_ARGS="--renderer blender" bash scripts/render_pbr.sh held_out "clean=10 OR=10 clutter=4"
# Needs the render extra (pip install -e '.[render]') and Debian's libllvm19. Without the shared
# machine's `cpu` wrapper the scenes simply run one after another.
set -euo pipefail
cd "$(dirname "$0")/.."
split="$1"; counts="${2:-clean=20 OR=20 clutter=20}"
read -r -a extra <<< "${RENDER_ARGS:-}"
run() { if command -v cpu >/dev/null 2>&1; then cpu "$@"; else "$@"; fi; }
for kc in $counts; do
  kind="${kc%%=*}"; n="${kc##*=}"
  for ((i = 0; i < n; i++)); do
    run .venv/bin/python -m monotracker.sim.pbr render --split "$split" --scene "$kind:$i" "${extra[@]}"
  done
done
.venv/bin/python -m monotracker.sim.pbr render --split "$split" --counts "$(echo "$counts" | tr ' ' ',')" "${extra[@]}"
