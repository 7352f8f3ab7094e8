#!/usr/bin/env bash
# The GPU figures in one short run (issues #16 and #26), as made on a lent H100/H200 machine whose image has
# CUDA JAX but none of jaxcal's pure-Python dependencies at the tested versions: those come as wheels in .whl/
# (pip download --no-deps equinox optimistix lineax jaxtyping wadler-lindig pyserial at constraints.txt's
# versions). Each part is bounded by `timeout`, so one part that runs long cannot cost the others;
# outputs go to $OUT (default ./gpu-out).
#   bash benchmarks/gpu_suite.sh
set -uo pipefail
OUT="${OUT:-gpu-out}"; mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH="/tmp/site:$PWD/src"
else
  export PYTHONPATH="$PWD/src"
fi
PY="${PY:-python3}"
export JAX_PLATFORMS="${JAX_PLATFORMS:-cuda}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/device.txt"
"$PY" -c "import jax, equinox, optimistix; print('jax', jax.__version__, jax.devices(), 'eqx', equinox.__version__, 'optx', optimistix.__version__)" | tee -a "$OUT/device.txt"
# 1. sweep throughput against batch size (torgau, 2,000 epochs, 0.5 and 0.25 m cells)
timeout "${T_SWEEP:-150}" "$PY" benchmarks/sweep_batching.py ${SWEEP_ARGS:-} | tee "$OUT/sweep_batching.jsonl"
# 2. the N-curve (whole calibrate processes), pgp then batch
timeout "${T_PGP:-150}" "$PY" benchmarks/large_networks.py --nodes "${PGP_NODES:-40,100,300}" --methods pgp \
  --timeout "${RUN_TIMEOUT:-70}" --out "$OUT/large-pgp" | tee "$OUT/large_pgp.jsonl"
timeout "${T_BATCH:-120}" "$PY" benchmarks/large_networks.py --nodes "${BATCH_NODES:-40,100}" --methods batch \
  --timeout "${RUN_TIMEOUT_BATCH:-100}" --out "$OUT/large-batch" | tee "$OUT/large_batch.jsonl"
echo "gpu_suite: done"
