#!/usr/bin/env bash
# What a lent CUDA GPU checks (docs/neural.md, "GPU"), in one run of 4 to 9 minutes (each step's
# limit below; together under the device's 10 minutes a command):
#   1. the CUDA tests (every test with "cuda" in its id: networks, training and the service on
#      the GPU against the CPU; CI has no GPU and skips them);
#   2. 1M-point queries of the shipped networks on the GPU, against the exact mesh on this CPU;
#   3. a 4D network of the bending arm trained on the GPU for a few minutes, then its accuracy at
#      random times and its 1M-point query (distance, normal, contact, velocity) on the GPU.
# Logs and the trained model go to $OUT (default runs/gpu). Run from the repository root with the
# project importable (installed, or PYTHONPATH=server:client).
#     bash benchmarks/gpu_check.sh [TRAIN_MINUTES]
set -uo pipefail
out=${OUT:-runs/gpu}
minutes=${1:-1.5}  # the 4D training's budget (its exact samples come first: ~20 s)
mkdir -p "$out"
export PYTHONUNBUFFERED=1
status=0
python3 - <<'EOF' 2>&1 | tee "$out/device.log" || status=1
import os, torch
print(torch.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else "no CUDA GPU",
      os.cpu_count(), "CPU cores")
EOF
timeout 200 python3 -m pytest -q -p no:cacheprovider -k cuda -rs \
    tests/engine/kinds/test_neural_grid.py tests/engine/kinds/test_neural_keyframes.py tests/engine/kinds/test_neural_deformed.py \
    tests/making/training/test_grid_training.py tests/making/training/test_animated_training.py \
    tests/service/test_queries.py tests/hard_cases/test_engine_hard_cases.py tests/engine/test_collider.py \
    2>&1 | tee "$out/tests.log" || status=1
timeout 120 python3 benchmarks/neural_query.py --device cuda --model bunny --rounds 5 \
    2>&1 | tee "$out/query.log" || status=1
arm=(--mesh examples/animations/arm.obj --animation examples/animations/arm.pc2 --fps 24 --loop)
timeout 150 python3 -m collider_cli train examples/animations/arm.obj --animation examples/animations/arm.pc2 \
    --fps 24 --loop --name arm4d-gpu --max-minutes "$minutes" --device cuda --models "$out" --quiet \
    2>&1 | tee "$out/train.log" || status=1
timeout 110 python3 benchmarks/animated_neural.py "$out/arm4d-gpu.safetensors" "${arm[@]}" --device cuda \
    --static models/bunny.safetensors --times 20 --points 20000 --rounds 5 --out "$out" \
    2>&1 | tee "$out/animated.log" || status=1
exit $status
