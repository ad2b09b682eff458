#!/usr/bin/env bash
# The GPU session's one command (~9 minutes at most): on an offline CUDA machine with torch, transformers,
# accelerate and peft preinstalled, from the repository root:
#   1. installs the carried pure-Python wheels (.whl/: datasets, dill, multiprocess; made by /work/shared/gpu/wheels.sh;
#      .whl/ is git-ignored, so a remote run must carry it) into /tmp/site and puts /tmp/site and the repo on PYTHONPATH;
#   2. prints the GPU and the versions;
#   3. (part `check`) python scripts/gpu_check.py (every stage through the CLI in bf16, the engine against
#      model.generate with its default and static cache; its own budget 450 s, under `timeout 480`)
#      -> $OUT/gpu_check.{log,json,md};
#   4. (part `tests`) the suite without the real tier on CUDA (`pytest -m "not real"`, 14 workers, under `timeout 300`;
#      SIGINT first so pytest still prints its summary; on an H200 on 2026-12-04 it took ~225 s)
#      -> $OUT/pytest.log, $OUT/junit.xml, $OUT/pytest_failures.txt;
#   5. prints the failing tests, then gpu_check's table (last, so a short output tail still shows it).
# A failure in one part does not stop the next; the exit status is 0 only when both parts passed.
#   bash scripts/gpu_run.sh                  # both parts (~13 min); OUT=/tmp/out unless set
#   bash scripts/gpu_run.sh check            # one part: `check` (~8 min) or `tests` (~5 min); where one command may
#   bash scripts/gpu_run.sh tests            #   run at most 10 minutes, run the two back to back
#   GPU_CHECK_ARGS=--quick PYTEST_TIMEOUT=300 PYTEST_WORKERS=12 bash scripts/gpu_run.sh
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-/tmp/out}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TRANSFORMERS_OFFLINE=1 \
       WANDB_MODE=disabled HF_HUB_DISABLE_TELEMETRY=1
PY="${PYTHON:-python3}"
start=$(date +%s)

# ---- 1. wheels
if ls .whl/*.whl >/dev/null 2>&1; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl 2>&1 | tail -3
else
  echo "gpu_run: no .whl/*.whl here (carry .whl); datasets must already be importable"
fi
export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"

# ---- 2. machine and versions
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -1
"$PY" - <<'PYEOF' 2>&1 | tee "$OUT/versions.txt"
import importlib, platform
out = [f"python {platform.python_version()}"]
for m in ("torch", "transformers", "accelerate", "peft", "datasets", "pytest", "xdist"):
    try:
        out.append(f"{m} {getattr(importlib.import_module(m), '__version__', '?')}")
    except Exception as e:
        out.append(f"{m} MISSING ({type(e).__name__})")
import torch
out.append(f"cuda {torch.version.cuda} available={torch.cuda.is_available()} "
           f"{torch.cuda.get_device_name(0) if torch.cuda.is_available() else ''}")
print(", ".join(out))
PYEOF

PARTS="${1:-check,tests}"
check_rc=0
test_rc=0

# ---- 3. gpu_check
if [[ ",$PARTS," == *",check,"* ]]; then
echo "== gpu_check (up to ${GPU_CHECK_TIMEOUT:-480} s)"
timeout -k 15 "${GPU_CHECK_TIMEOUT:-480}" "$PY" scripts/gpu_check.py --json "$OUT/gpu_check.json" ${GPU_CHECK_ARGS:-} \
  > "$OUT/gpu_check.log" 2>&1
check_rc=$?
grep '^\[gpu_check\]' "$OUT/gpu_check.log" | cut -c1-200 | tail -40
grep -B1 -A200 '^| row | status' "$OUT/gpu_check.log" > "$OUT/gpu_check.md" || true
echo "gpu_check exit $check_rc after $(( $(date +%s) - start )) s"
fi

# ---- 4. the suite on CUDA
if [[ ",$PARTS," == *",tests,"* ]]; then
echo "== pytest -m 'not real' (up to ${PYTEST_TIMEOUT:-300} s)"
workers=(-n "${PYTEST_WORKERS:-14}")
if ! "$PY" -c "import xdist" 2>/dev/null; then  # pyproject's addopts has -n auto: without xdist, plain addopts
  workers=(-o "addopts=-ra --strict-markers --import-mode=importlib")
fi
timeout -s INT -k 20 "${PYTEST_TIMEOUT:-300}" "$PY" -m pytest -m "not real" -q "${workers[@]}" -rfE --tb=short --no-header \
  -p no:cacheprovider --junitxml="$OUT/junit.xml" tests/posttrain tests/recipes tests/scripts > "$OUT/pytest.log" 2>&1
test_rc=$?
grep -E '^(FAILED|ERROR) ' "$OUT/pytest.log" > "$OUT/pytest_failures.txt" || true
echo "pytest exit $test_rc ($([ $test_rc = 124 ] || [ $test_rc = 130 ] && echo 'stopped at its time limit' || echo done))"
tail -n 40 "$OUT/pytest.log" | cut -c1-240
fi

# ---- 5. gpu_check's table, last
if [ -f "$OUT/gpu_check.md" ]; then
  echo "== gpu_check table ($OUT/gpu_check.md)"
  cut -c1-400 "$OUT/gpu_check.md"
fi
echo "gpu_run: gpu_check exit $check_rc, pytest exit $test_rc, $(( $(date +%s) - start )) s in all"
[ "$check_rc" = 0 ] && [ "$test_rc" = 0 ]
