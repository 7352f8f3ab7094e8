#!/usr/bin/env bash
# Build the documentation site into site/ with `mkdocs build --strict` (broken links, missing API
# references and docstrings griffe cannot parse fail the build). Installs the docs extra into .venv at
# the tested versions of constraints.txt first (after scripts/setup.sh). Extra arguments go to mkdocs
# build. Nothing is downloaded at build time: no CDN, no fonts (theme.font: false), no privacy plugin;
# the notebooks are rendered from their stored outputs (execute: false).
#   bash scripts/docs.sh                   # build site/
#   .venv/bin/mkdocs serve                 # then: a live preview at http://127.0.0.1:8000
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install-extra.sh docs
export NO_MKDOCS_2_WARNING=1 JAX_PLATFORMS="${JAX_PLATFORMS:-cpu}"
start=$(date +%s)
.venv/bin/mkdocs build --strict "$@"
echo "docs: built site/ in $(( $(date +%s) - start )) s"
