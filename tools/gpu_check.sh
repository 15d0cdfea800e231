#!/usr/bin/env bash
# The GPU checks in one run, for a machine with an NVIDIA GPU and its own CUDA build of torch
# (no package index needed): the device tests, the whole suite, and tools/bench_gpu.py.
#   WHEELS=dir   wheels to install first into /tmp/site (what the machine lacks: kornia, ...)
#   TORCHTRACK_DATA=dir   holds tracking/bobot_pedestrian for the benchmark's SIR frame and eval
#   OUT=dir      where the logs go (default ./runs/gpu_check)
# Usage: bash tools/gpu_check.sh [devices|bench|suite|profile ...]   (default: devices suite bench)
#   suite: the whole test suite, every test's result on its own line (-v), so a run cut short
#   still names its failures; profile: the CUDA kernels and host syncs of the SIR step and of a
#   multi-target frame (torch.profiler), to see what a GPU step is spent on; pets: the main job
#   (`torchtrack track --detect pedestrian`, seed 0) on PETS09-S2L1 on each of PETS_DEVICES
#   (default: cuda cpu), scored by `torchtrack eval --mot` (needs videos/pets2009_s2l1_vtest and
#   mot/PETS09-S2L1 under TORCHTRACK_DATA)
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${OUT:-runs/gpu_check}"; mkdir -p "$OUT"
if [ -n "${WHEELS:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$WHEELS"/*.whl || exit 1
  export PYTHONPATH=$PWD:/tmp/site${PYTHONPATH:+:$PYTHONPATH}  # this checkout before any wheel of it
fi
export PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.is_available(), torch.cuda.get_device_name(0))"
steps=("${@:-devices suite bench}"); steps=(${steps[@]})
for s in "${steps[@]}"; do
  case $s in
    devices) timeout 300 python3 -m pytest -q -rfEs -p no:cacheprovider tests/test_devices.py \
               tests/filter/test_sir.py tests/filter/test_resample.py -k "device or cuda" \
               2>&1 | tee "$OUT/devices.log" | tail -60 ;;
    suite) OMP_NUM_THREADS=1 TORCHTRACK_DATA=/nonexistent timeout "${SUITE_TIMEOUT:-600}" python3 -m pytest -p no:cacheprovider \
             -n 16 -p no:benchmark -v -rfE --tb=short 2>&1 | tee "$OUT/suite.log" \
             | grep -E "FAILED|ERROR|passed|failed" | tail -40 ;;
    bench) timeout 300 python3 tools/bench_gpu.py 2>&1 | tee "$OUT/bench.log" | tail -14 ;;
    profile) timeout 300 python3 tools/bench_gpu.py --devices cuda --only sir multi --reps 5 \
               --multi-frames 8 --profile 2>&1 | tee "$OUT/profile.log" | tail -60 ;;
    pets) d="${TORCHTRACK_DATA:-../shared/data}"
          for dev in ${PETS_DEVICES:-cuda cpu}; do
            echo "## PETS09-S2L1, torchtrack track on $dev"
            timeout "${PETS_TIMEOUT:-200}" python3 -m torchtrack track \
              "$d/videos/pets2009_s2l1_vtest/vtest.avi" --detect pedestrian --seed 0 \
              --device "$dev" --no-progress --mot "$OUT/pets_$dev.txt" 2>&1 | tee "$OUT/pets_$dev.log" | tail -5
            [ -s "$OUT/pets_$dev.txt" ] && timeout 120 python3 -m torchtrack eval --mot \
              "$d/videos/pets2009_s2l1_vtest/vtest.avi" --gt "$d/mot/PETS09-S2L1/gt/gt.txt" \
              --results "$OUT/pets_$dev.txt" -o "$OUT/mot_$dev" 2>&1 | tail -8
          done ;;
  esac
done
