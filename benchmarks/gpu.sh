#!/usr/bin/env bash
# The GPU checks in one script (at most ~8 minutes on one device): the CUDA tests, env steps/s at
# N up to 2^22, the fused learner, batched seeds on CUDA and a short Figure 4 run on CUDA. Every
# figure goes to one results file, ${OUT:-.}/gpu-results.txt (docs/benchmarks.md records them).
#
#   bash benchmarks/gpu.sh            # on a machine with CUDA, from the repository root
set -uo pipefail
OUT_DIR="${OUT:-.}"
RESULTS="$OUT_DIR/gpu-results.txt"
PY="${PYTHON:-python}"
mkdir -p "$OUT_DIR"
: > "$RESULTS"
section() { echo "== $1 ($(date -u +%H:%M:%S))" | tee -a "$RESULTS"; }
run() { timeout "$1" "${@:2}" 2>&1 | tail -n 40 | tee -a "$RESULTS"; }

section "device"
run 30 nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
run 30 "$PY" -c "import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"
git rev-parse HEAD 2>/dev/null | tee -a "$RESULTS"

section "CUDA tests"
run 120 "$PY" -m pytest -q -p no:cacheprovider tests/test_cuda.py

section "windy env steps/s on CUDA, N = 2^10 .. 2^22"
run 90 "$PY" - <<'PY'
import time, torch
from taskvar_torch.envs import WindyGridEnv
for p in (10, 14, 18, 20, 22):
    n = 1 << p
    env = WindyGridEnv(num_envs=n, seed=0, device="cuda", validate_actions=False)
    td = env.reset()
    a = torch.randint(0, 4, (n,), device="cuda")
    for _ in range(5):
        td["action"] = a; _, td = env.step_and_maybe_reset(td)
    torch.cuda.synchronize(); t = time.perf_counter(); steps = 50
    for _ in range(steps):
        td["action"] = a; _, td = env.step_and_maybe_reset(td)
    torch.cuda.synchronize(); dt = time.perf_counter() - t
    print(f"N=2^{p:<3} {n * steps / dt / 1e6:8.1f} M steps/s")
PY

section "env throughput script on CUDA"
run 90 "$PY" benchmarks/env_throughput.py --device cuda --threads 1

section "batched seeds on CUDA (windy 5x5, N = 1, 5, 10)"
run 150 "$PY" benchmarks/seeds.py --cases windy5 --seeds 1,5,10 --device cuda

section "Figure 4 quick run on CUDA"
run 90 "$PY" -m taskvar_torch.cli experiment wargus-fig4 device=cuda --quick --out "$OUT_DIR/fig4-cuda"

section "done"
