#!/usr/bin/env bash
# Lint, format and type check (ruff: the rules and width in pyproject.toml; mypy: [tool.mypy] there): what CI runs after the tests and
# what the pre-commit hooks run. Installs the lint extra into .venv at the tested version first.
#   bash scripts/lint.sh                 # check only (non-zero exit on a finding)
#   .venv/bin/ruff format src tests benchmarks && .venv/bin/ruff check --fix src tests benchmarks
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-extra.sh lint
.venv/bin/ruff check src tests benchmarks
.venv/bin/ruff format --check src tests benchmarks
.venv/bin/mypy
echo "lint: ruff check, ruff format --check and mypy clean"
