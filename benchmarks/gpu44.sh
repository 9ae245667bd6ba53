#!/usr/bin/env bash
# Issue 44 (trained policies as controllers) on a one-GPU host: the policy controller's period
# against a joint_trajectory_controller's at 1024 and 4096 worlds on warp (and mjx at 1024),
# what reading the state to the host costs beside it, and ONNX Runtime's call alone. After
# gpu43.sh's copy1, copy2 and install stages (the machine warm), one device call each:
#
#   carry [".whlort"]   bash benchmarks/gpu44.sh ort      # ONNX Runtime's CPU wheel and its needs
#   carry []            bash benchmarks/gpu44.sh policy
#
# .whlort/ holds onnxruntime (the version of this checkout's .venv), flatbuffers, packaging,
# protobuf, coloredlogs, humanfriendly as cp312 manylinux wheels (pip download, as the device
# README says). ONNX Runtime's CUDA provider (onnxruntime-gpu, hundreds of MiB) does not fit a
# call: inference runs on the host's CPU, the observation read from the device each period.
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W, warm; the stages copy1 and copy2
quiet() { grep --line-buffered -v "^Warp \|^Module \|SCHED_FIFO"; }

case $stage in
ort)
  warm
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /root/site \
    "$W"/.whlort/*.whl 2>&1 | tail -2
  python3 -c "import onnxruntime as o; print('onnxruntime', o.__version__, o.get_available_providers())"
  ;;
policy)
  warm
  {
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    timeout 330 python3 benchmarks/policy.py --backend warp --worlds 1024,4096 --seconds 3 --warmup 1
    timeout 200 python3 benchmarks/policy.py --backend mjx --worlds 1024 --seconds 3 --warmup 1
  } 2>&1 | quiet | tee "$OUT/policy.log"
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
