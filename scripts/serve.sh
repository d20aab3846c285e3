#!/usr/bin/env bash
# Installs what is needed, then runs the MonoTracker web app on the bundled sample CT with the
# simulated camera and robot (http://127.0.0.1:8080). Extra arguments go to `monotracker serve`,
# e.g. --pin 1234 (otherwise a random arming PIN is printed here).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/monotracker serve --sample --camera sim --robot sim "$@"
