#!/usr/bin/env bash
# Installs what is needed, then runs MonoTracker on the bundled sample data.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/monotracker detect-ct sample_data/phantom_ct.nii.gz "$@"
