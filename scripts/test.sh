#!/usr/bin/env bash
# Set up .venv (if needed) and run the whole test suite. Extra arguments go to pytest.
# The tests run in parallel (pytest-xdist, one worker per core; `worksteal`: an idle worker takes tests
# queued on a busy one); JAXCAL_TEST_WORKERS=0 runs them in this process, one after another. The 30 slowest
# tests are listed at the end (to keep the suite within its time).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export JAX_PLATFORMS="${JAX_PLATFORMS:-cpu}"
exec .venv/bin/python -m pytest -n "${JAXCAL_TEST_WORKERS:-auto}" --dist worksteal --durations=30 "$@"
