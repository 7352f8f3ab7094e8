#!/usr/bin/env bash
# The GPU figures in one short run (issues #16, #26 and #19), as made on a lent H100/H200 machine whose image has
# CUDA JAX but none of jaxcal's pure-Python dependencies at the tested versions: those come as wheels in .whl/
# (pip download --no-deps equinox optimistix lineax jaxtyping wadler-lindig pyserial blackjax optax absl-py tqdm
# threadpoolctl at constraints.txt's versions). Each part is bounded by `timeout`, so one part that runs long cannot cost the others;
# outputs go to $OUT (default ./gpu-out). A part whose bound is 0 is skipped (e.g. T_SWEEP=0).
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
part() {  # part BOUND_S LOG CMD...: run CMD under `timeout BOUND_S`, its output teed to $OUT/LOG; skipped if BOUND_S is 0
  local bound="$1" log="$2"; shift 2
  if [ "$bound" = 0 ]; then echo "gpu_suite: skipped $log"; return; fi
  timeout "$bound" "$@" | tee "$OUT/$log"
}
export JAX_PLATFORMS="${JAX_PLATFORMS:-cuda}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/device.txt"
"$PY" -c "import jax, equinox, optimistix, blackjax; print('jax', jax.__version__, jax.devices(), 'eqx', equinox.__version__, 'optx', optimistix.__version__, 'blackjax', blackjax.__version__)" | tee -a "$OUT/device.txt"
# 1. sweep throughput against batch size (torgau, 2,000 epochs, 0.5 and 0.25 m cells)
part "${T_SWEEP:-150}" sweep_batching.jsonl "$PY" benchmarks/sweep_batching.py ${SWEEP_ARGS:-}
# 2. the N-curve (whole calibrate processes), pgp then batch
part "${T_PGP:-150}" large_pgp.jsonl "$PY" benchmarks/large_networks.py --nodes "${PGP_NODES:-40,100,300}" \
  --methods pgp --timeout "${RUN_TIMEOUT:-70}" --out "$OUT/large-pgp"
part "${T_BATCH:-120}" large_batch.jsonl "$PY" benchmarks/large_networks.py --nodes "${BATCH_NODES:-40,100}" \
  --methods batch --timeout "${RUN_TIMEOUT_BATCH:-100}" --out "$OUT/large-batch"
# 3. trajectory GP against nls, 10 anchors from ~1e5 ranges (issue #19 item 3), default gp then model=space
part "${T_GP:-0}" gp_speed.jsonl "$PY" benchmarks/gp_speed.py --rate 150 --n 300
part "${T_GP_SPACE:-0}" gp_speed_space.jsonl "$PY" benchmarks/gp_speed.py --rate 150 --n 300 --model space
part "${T_GP_EXCESS:-0}" gp_speed_excess.jsonl "$PY" benchmarks/gp_speed.py --rate 150 --n 300 --model excess
# 4. tuning (issue #17's user): the whole `jaxcal tune` process on torgau (the README's command), on the GPU with an
# empty compile cache, then the same machine's CPU cores (JAX_PLATFORMS=cpu, its own empty cache), then the GPU again
# with its cache warm; wall seconds and the summary line of each
tune() {  # tune BOUND_S NAME PLATFORM CACHE
  local bound="$1" name="$2"
  if [ "$bound" = 0 ]; then echo "gpu_suite: skipped $name"; return; fi
  local t0; t0=$(date +%s.%N)
  JAX_PLATFORMS="$3" JAXCAL_CACHE_DIR="$4" timeout "$bound" "$PY" -m jaxcal.cli tune data/torgau.h5 --method pgp \
    --config conf1 -o "$OUT/$name.json" > "$OUT/$name.log" 2>&1
  local rc=$?
  echo "{\"part\": \"$name\", \"platform\": \"$3\", \"rc\": $rc, \"wall_s\": $("$PY" -c "import time; print(round(time.time() - $t0, 1))")}" \
    | tee -a "$OUT/tune.jsonl"
  tail -n 3 "$OUT/$name.log"
}
tune "${T_TUNE_GPU:-0}" tune-gpu-cold cuda /tmp/jaxcal-cache-gpu
tune "${T_TUNE_CPU:-0}" tune-cpu-cold cpu /tmp/jaxcal-cache-cpu
tune "${T_TUNE_GPU_WARM:-0}" tune-gpu-warm cuda /tmp/jaxcal-cache-gpu
echo "gpu_suite: done"
