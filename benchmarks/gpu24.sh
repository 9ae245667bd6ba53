#!/usr/bin/env bash
# Issue 24 (speed on every card) on a one-GPU host (nvidia-h100-x1 or nvidia-h200): the stages
# of one GPU session, one device call each, chained while the machine is warm (it goes cold
# ~30 s after a call). Each stage fits the 600 s a call may run.
# Staged here first: bash ../shared/gpu/stage-wheels.sh; bash ../shared/gpu/stage-ros-wheels.sh;
# .whlx/pure.tgz (catkin_pkg, docutils, pyparsing, dateutil, empy from .venv's site-packages).
#
#   carry [".whl1"]                  bash benchmarks/gpu24.sh copy1
#   carry [".whl2", export]          bash benchmarks/gpu24.sh copy2
#   carry [".whl3", export]          bash benchmarks/gpu24.sh install    # the card, the cores
#   carry [".whlros",".whlx",export] bash benchmarks/gpu24.sh ros        # ROS 2 and the interfaces
#   carry [export]                   bash benchmarks/gpu24.sh fleet      # flat out at 1024 arms, twice; 4096 at 25 Hz
#   carry [export]                   bash benchmarks/gpu24.sh contract   # warp against raw MuJoCo Warp, both tools
#   carry [export]                   bash benchmarks/gpu24.sh loops      # the controllers' burst, the sensor loop
#   carry [export]                   bash benchmarks/gpu24.sh cold       # 1024 rovers from an empty kernel cache, then warm
#
# Everything printed also goes to $OUT/<stage>.log. WHEELS: the folder holding the staged
# .whl*/ folders (default: here). Run from a clean export of a commit, carried
# (`git archive HEAD | tar -x -C .gpu24`), so that edits in progress stay out:
#   cd .gpu24 && WHEELS=.. bash benchmarks/gpu24.sh fleet
# The figures, with the card named beside each, go to benchmarks/RESULTS.md; a figure from the
# other card is compared only after its baseline ran again on this one.
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W, warm; the stages copy1 and copy2
# Warp's per-module lines and the container's SCHED_FIFO refusal say nothing about speed
quiet() { grep -v "^Warp \|^Module \|SCHED_FIFO"; }

case $stage in
install)
  {
    bash "$W"/.whl3/install.sh 2>&1 | tail -2
    python3 -m pip install -q --no-deps --no-build-isolation -e . 2>&1 | tail -2  # batchsim.models
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    nproc
    lscpu | grep -i "model name\|thread(s) per core"
  } 2>&1 | tee "$OUT/install.log"
  ;;
ros)
  warm
  {
    tar xzf "$W"/.whlx/pure.tgz -C /root/site
    python3 -m pip install -q --no-index --no-deps --no-compile "$W"/.whlros/*.whl
    python3 -m pip install -q --no-deps --no-build-isolation -e . >/dev/null
    python3 -m ros_bridge.interfaces --require --jobs 16 2>&1 | tail -1
    python3 -c "import rclpy; print('rclpy imports')"
  } 2>&1 | tee "$OUT/ros.log"
  ;;
fleet)
  warm
  {
    for run in 1 2; do  # flat out, with ROS against without; the loop on core 0, the rest off it
      timeout 280 python3 benchmarks/fleet.py --backend warp --model arm --worlds 1024 --control-rate 100 \
        --publish-rate 100 --subscriber-processes 8 --seconds 10 --cpu-affinity 0
    done
    timeout 280 python3 benchmarks/fleet.py --backend warp --model arm --worlds 4096 --control-rate 100 \
      --publish-rate 25 --subscriber-processes 8 --seconds 12
  } 2>&1 | quiet | tee "$OUT/fleet.log"
  ;;
contract)
  warm
  {
    timeout 280 python3 benchmarks/throughput.py --backends warp --worlds 8192 --model humanoid --rounds 5 \
      --seconds 4 --out "$OUT"
    timeout 300 python3 benchmarks/period_profile.py --backend warp --worlds 8192 --model humanoid --periods 200 --rounds 3
  } 2>&1 | quiet | tee "$OUT/contract.log"
  ;;
loops)
  warm
  {
    timeout 200 python3 benchmarks/controllers.py --backend warp --models arm --cases burst --worlds 1024,4096 \
      --seconds 8 --no-handover
    timeout 200 python3 benchmarks/sensors.py --backends warp --no-camera --no-lidar --loop 1024 --loop-size 64x64 \
      --loop-seconds 6 --json "$OUT/sensors.json"
  } 2>&1 | quiet | tee "$OUT/loops.log"
  ;;
cold)
  warm
  {
    timeout 390 python3 benchmarks/cold_start.py --worlds 1024 --seconds 20 --domain 71
    timeout 180 python3 benchmarks/cold_start.py --worlds 1024 --seconds 10 --domain 72 --keep-cache
  } 2>&1 | quiet | tee "$OUT/cold.log"
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
