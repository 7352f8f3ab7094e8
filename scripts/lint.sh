#!/usr/bin/env bash
# Lint and format check (ruff: the rules and width in pyproject.toml): what CI runs after the tests and
# what the pre-commit hooks run. Installs the lint extra into .venv at the tested version first.
#   bash scripts/lint.sh                 # check only (non-zero exit on a finding)
#   .venv/bin/ruff format src tests benchmarks && .venv/bin/ruff check --fix src tests benchmarks
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
stamp=.venv/.jaxcal-lint-installed
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[lint]"
  echo "$want" > "$stamp"
fi
.venv/bin/ruff check src tests benchmarks
.venv/bin/ruff format --check src tests benchmarks
echo "lint: ruff check and ruff format --check clean"
