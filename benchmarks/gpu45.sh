#!/usr/bin/env bash
# Issue 45 (re-simulation and calibration) on a one-GPU host (nvidia-h100-x1 or nvidia-h200): the
# stages of one GPU session, one device call each, chained while the machine is warm (~30 s).
# Staged as gpu43.sh stages, plus the recording's wheels (mcap, mcap-ros2-support, zstandard, lz4):
#   pip download --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 \
#     --no-deps -d .whlrec zstandard==0.25.0 mcap==1.6.0 mcap-ros2-support==0.6.0 lz4==4.4.5
#
#   carry [".whl1"]                            bash benchmarks/gpu45.sh copy1
#   carry [".whl2", export]                    bash benchmarks/gpu45.sh copy2
#   carry [".whl3", export]                    bash benchmarks/gpu45.sh install
#   carry [".whlros",".whlx",".whlrec",export] bash benchmarks/gpu45.sh ros
#   carry [export]                             bash benchmarks/gpu45.sh record     # what recording the inputs costs 1024 arms on warp
#   carry [export]                             bash benchmarks/gpu45.sh resim      # a warp recording re-run on the host's CPU
#   carry [export]                             bash benchmarks/gpu45.sh calibrate  # calibration rounds on warp, and on the host's cores
#   carry [export]                             bash benchmarks/gpu45.sh parting    # why the arm-and-rover worlds part more on the card
#
# Everything printed also goes to $OUT/<stage>.log. Run from a clean export of a commit
# (`git archive HEAD | tar -x -C .gpu45`): cd .gpu45 && WHEELS=.. bash benchmarks/gpu45.sh record
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W, warm; the stages copy1 and copy2
quiet() { grep --line-buffered -v "^Warp \|^Module \|SCHED_FIFO"; }
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

case $stage in
install) bash "$(dirname "$0")/gpu24.sh" install ;;
ros)
  bash "$(dirname "$0")/gpu24.sh" ros
  python3 -m pip install -q --no-index --no-deps --no-compile "$W"/.whlrec/*.whl 2>&1 | tail -2
  python3 -c "import mcap, mcap_ros2, zstandard; print('mcap', mcap.__version__)" | tee -a "$OUT/ros.log"
  ;;
record)
  warm
  {
    nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
    timeout 560 python3 benchmarks/recording.py --worlds 1024 --backend warp --control-rate 100 --duration 10 --warmup
  } 2>&1 | quiet | tee "$OUT/record.log"
  ;;
resim)
  warm
  {
    nvidia-smi --query-gpu=name --format=csv,noheader
    printf 'randomize:\n  seed: 0\n  fields:\n    - field: body_mass\n      scale: {uniform: [0.8, 1.2]}\n    - field: dof_damping\n      scale: {loguniform: [0.5, 2.0]}\n  start_pose:\n    add: {normal: [0.0, 0.1]}\n' > /tmp/rand.yaml
    cat /tmp/rand.yaml
    rm -f /tmp/warp.mcap
    ROS_DOMAIN_ID=45 timeout 300 batchsim --backend warp --worlds 256 --randomize /tmp/rand.yaml --record /tmp/warp.mcap \
      --record-worlds 0-7,255 --duration 10 --rtf 0 --quiet
    timeout 200 batchsim resim /tmp/warp.mcap --tolerance 1e-3 --json "$OUT/resim_warp.json"
    timeout 200 batchsim resim /tmp/warp.mcap --worlds 0 --tolerance 1e-6
  } 2>&1 | quiet | tee "$OUT/resim.log"
  ;;
calibrate)
  warm
  {
    nvidia-smi --query-gpu=name --format=csv,noheader
    timeout 330 python3 benchmarks/calibration.py --backend warp --grid 128x5,1024x5,4096x5
    timeout 200 python3 benchmarks/calibration.py --backend cpu --grid 128x5,1024x5
  } 2>&1 | quiet | tee "$OUT/calibrate.log"
  ;;
parting)
  # On the H100 (2026-12-05) the depot's arm-and-rover worlds, recorded on warp and re-run on C
  # MuJoCo, parted by 9.4e-3 rad/s in a wheel's velocity at the first period; on warp's CPU
  # device by 5.7e-5, as the warehouse worlds did on both. Which of these parts as much?
  warm
  run() {  # name, batchsim args...: 2 worlds for 0.3 s on warp, recorded; world 0 re-run on the host
    name=$1
    shift
    rm -f /tmp/$name.mcap
    echo "== $name: $*"
    ROS_DOMAIN_ID=47 timeout 150 batchsim "$@" --worlds 2 --backend warp --record /tmp/$name.mcap --duration 0.3 \
      --rtf 0 --controllers default 2>&1 | grep "compiling\|grew\|overflow\|recording:\|error"
    timeout 60 batchsim resim /tmp/$name.mcap --worlds 0 --tolerance 1e-4 2>&1 | grep "world 0"
  }
  {
    nvidia-smi --query-gpu=name --format=csv,noheader
    run cells --fleet examples/fleets/arm_and_rover.yaml
    run cells_det --fleet examples/fleets/arm_and_rover.yaml --deterministic
    run rover --model rover
    run cells_big --fleet examples/fleets/arm_and_rover.yaml --nconmax 64 --njmax 600
    run arm --model arm
  } 2>&1 | quiet | tee "$OUT/parting.log"
  ;;
*) echo "unknown stage $stage" ;;
esac
