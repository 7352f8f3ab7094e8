#!/usr/bin/env bash
# Install an optional extra of jaxcal (docs, lint) into .venv at the tested versions of constraints.txt,
# after scripts/setup.sh; idempotent (a stamp per extra hashes pyproject.toml and constraints.txt).
#   bash scripts/install-extra.sh docs
set -euo pipefail
cd "$(dirname "$0")/.."
extra="${1:?usage: install-extra.sh EXTRA}"
bash scripts/setup.sh
stamp=".venv/.jaxcal-${extra}-installed"
want=$(cat pyproject.toml constraints.txt | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[${extra}]"
  echo "$want" > "$stamp"
fi
