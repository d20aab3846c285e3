#!/usr/bin/env bash
# Compiles the package's numba kernels into their disk cache (app/monotracker/engine/kernels.py),
# one process per kernel group side by side (~31 s on 2 cores after an install; ~1.5 s when
# cached). Run by setup.sh after an install and by test.sh before the tests. A failure is only a
# warning: the kernels then compile at first use, as without this step.
set -uo pipefail
cd "$(dirname "$0")/.."
rc=0
.venv/bin/monotracker compile-kernels --quiet --side-by-side || rc=$?
if [ "$rc" != 0 ]; then
  echo "warning: compiling the kernels ahead failed (exit $rc); they compile at first use instead" >&2
fi
exit 0
