#!/usr/bin/env bash
# Issue 27 on a 4-GPU host (nvidia-h100-x4 / nvidia-h200-x4): the stages of one GPU session,
# one device call each, chained while the machine is warm (it goes cold ~30 s after a call).
# Staged here first: bash ../shared/gpu/stage-wheels.sh; bash ../shared/gpu/stage-ros-wheels.sh;
# .whlx/pure.tgz (catkin_pkg, docutils, pyparsing, dateutil, empy from .venv's site-packages).
#
#   carry [".whl1"]            bash benchmarks/gpu27.sh copy1
#   carry [".whl2"]            bash benchmarks/gpu27.sh copy2
#   carry [".whl3"]            bash benchmarks/gpu27.sh install
#   carry [".whlros",".whlx"]  bash benchmarks/gpu27.sh bench    # ROS set up, checks, devices.py
#   (nothing carried)          bash benchmarks/gpu27.sh fleet [WORLDS...]   # ros_stack.py over 4 GPUs
#
# Everything printed also goes to $OUT (bench.log, devices.csv, fleet.log). WHEELS: the folder
# holding the staged .whl*/ folders (default: here); run from a clean export of a commit
# (`git archive HEAD | tar -x -C .gpu27`, carried) so that others' edits in progress stay out:
#   cd .gpu27 && WHEELS=.. bash benchmarks/gpu27.sh bench
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W; the stages copy1 and copy2

case $stage in
install) bash "$W"/.whl3/install.sh ;;
bench)
  warm
  {
    set -x
    nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv
    nvidia-smi topo -m | head -6
    nproc
    tar xzf "$W"/.whlx/pure.tgz -C /root/site
    python3 -m pip install -q --no-index --no-deps --no-compile "$W"/.whlros/*.whl
    python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null
    time python3 -m ros_bridge.interfaces --require --jobs 16 | tail -2
    set +x
    # the fleet's shared arrays page-locked for the GPUs, and a 2-GPU fleet of shard
    # processes reading through them: the same arm physics as one GPU (float32 rounding)
    python3 - <<'PY'
import time
import numpy as np
import warp as wp
import batchsim
from batchsim.backends.warp import host

a = np.zeros((4096, 139))
locked = host.lock_pages(a, wp.get_device("cuda:0"))
print("fleet memory page-locked:", locked is not None)
host.unlock_pages(locked, wp.get_device("cuda:0"))
t = time.time()
fleets = [batchsim.make("arm", 512, "warp", devices=["cuda:0", "cuda:1"], processes=True), batchsim.make("arm", 512, "warp", device="cuda:0")]
for sim in fleets:
    sim.configure(); sim.activate()
    sim.command[:] = np.random.default_rng(1).uniform(-0.3, 0.3, sim.command.shape)
    for _ in range(20):
        sim.write(); sim.step(10); sim.read()
err = np.abs(fleets[0].state - fleets[1].state).max()
size = np.abs(fleets[1].state).max()
print(f"2 GPUs (shard processes) against 1 GPU, 512 arms, 200 steps: max |state difference| {err:.2e} (|state| up to {size:.2f}); {time.time() - t:.0f} s with the compile")
for sim in fleets:
    sim.shutdown()
PY
    python3 benchmarks/devices.py --devices 0,1,2,3 --worlds 8192 --model humanoid --seconds 3 \
      --shards processes,processes --counts 1,2,4 --out "$OUT"
  } 2>&1 | tee "$OUT/bench.log"
  ;;
fleet)
  warm
  for worlds in "${@:-8192}"; do
    python3 benchmarks/ros_stack.py --backend warp --devices 0,1,2,3 --worlds "$worlds" --subscribers 16 \
      --goals none --seconds 10 --warmup 10 --thread-priority 0 2>&1 | tee -a "$OUT/fleet.log"
  done
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
