#!/usr/bin/env bash
# Set up .venv (if needed) and run the main job: `jaxcal demo` on the embedded default scenario.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export JAX_PLATFORMS="${JAX_PLATFORMS:-cpu}"
exec .venv/bin/jaxcal demo "$@"
