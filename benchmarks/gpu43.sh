#!/usr/bin/env bash
# Issue 43 (several robots in one world) on a one-GPU host (nvidia-h200 or nvidia-h100-x1): the
# stages of one GPU session, one device call each, chained while the machine is warm (it goes cold
# ~30 s after a call). Each stage fits the 600 s a call may run. The same staging as gpu24.sh:
# bash ../shared/gpu/stage-wheels.sh; bash ../shared/gpu/stage-ros-wheels.sh; and .whlx/pure.tgz,
#   tar czf .whlx/pure.tgz --exclude=__pycache__ -C .venv/lib/python3.11/site-packages \
#     catkin_pkg catkin_pkg-*.dist-info docutils docutils-*.dist-info pyparsing pyparsing-*.dist-info \
#     dateutil python_dateutil-*.dist-info em.py emdoc.py emhelp.py emlib.py empy-*.dist-info
#
#   carry [".whl1"]                  bash benchmarks/gpu43.sh copy1      # from the checkout: .whl1 and
#                                                                        # the export together pass 64 MiB
#   carry [".whl2", export]          bash benchmarks/gpu43.sh copy2
#   carry [".whl3", export]          bash benchmarks/gpu43.sh install    # gpu24.sh's: the card, the cores
#   carry [".whlros",".whlx",export] bash benchmarks/gpu43.sh ros        # gpu24.sh's: ROS 2, the interfaces
#   carry [export]                   bash benchmarks/gpu43.sh physics [arm] [rover] [rover-cg] [cpu]   # default: arm rover cpu
#   carry [export]                   bash benchmarks/gpu43.sh fleet      # 1024 worlds x 4 arms over ROS, 100 Hz
#   carry [export]                   bash benchmarks/gpu43.sh kernels [VARIANT...]  # default: "default"
#
# physics: benchmarks/fleet_robots.py physics, K robots a world against K worlds of one (K = 4, 8),
# 8192 robots on warp (the arm, then the rover), then 1024 rovers on the host's CPU for comparison.
# Each part fits one call alone if the kernel compile makes all three too long for one.
# fleet: the issue's GPU target, 1024 worlds x 4 arms at RTF 1 with joint_states at 100 Hz, counted
# by 8 subscriber processes (one took only 6 % of 410k messages/s on 2026-12-02).
# kernels: robots_per_world_kernels.py, the rover's K robots a world against K worlds of one in raw
# MuJoCo Warp with its event trace per phase; each VARIANT ("default", "opt.solver=cg", ...) against
# its own one-robot layout (one compile per model and variant: split over calls).
# Everything printed also goes to $OUT/<stage>.log. WHEELS: the folder holding the staged .whl*/
# folders (default: here). Run from a clean export of a commit, carried
# (`git archive HEAD | tar -x -C .gpu43`), so that edits in progress stay out:
#   cd .gpu43 && WHEELS=.. bash benchmarks/gpu43.sh physics
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W, warm; the stages copy1 and copy2
# Warp's per-module lines and the container's SCHED_FIFO refusal say nothing about speed
quiet() { grep --line-buffered -v "^Warp \|^Module \|SCHED_FIFO"; }

case $stage in
install | ros) bash "$(dirname "$0")/gpu24.sh" "$stage" ;;  # the same commands as issue 24's session
physics)
  warm
  parts=${*:-arm rover cpu}
  {
    for part in $parts; do
      case $part in
      arm | rover)
        timeout 290 python3 benchmarks/fleet_robots.py physics --backend warp --model "$part" --robots 4,8 \
          --total 8192 --seconds 8 ;;
      rover-cg)  # the same on floors whose option sets MuJoCo's CG solver (the default is Newton)
        timeout 290 python3 benchmarks/fleet_robots.py physics --backend warp --model rover --robots 4,8 \
          --total 8192 --seconds 8 --solver CG ;;
      cpu)
        timeout 120 python3 benchmarks/fleet_robots.py physics --backend cpu --model rover --robots 4,8 \
          --total 1024 --seconds 5 ;;
      *) echo "unknown physics part $part" ;;
      esac
    done
  } 2>&1 | quiet | tee "$OUT/physics.log"
  ;;
fleet)
  warm
  {
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    timeout 540 python3 benchmarks/fleet_robots.py ros --fleet examples/fleets/four_arms.yaml --worlds 1024 \
      --rate 100 --backend warp --seconds 15 --warmup 10 --subscriber-processes 8
  } 2>&1 | quiet | tee "$OUT/fleet.log"
  ;;
kernels)
  warm
  {
    for variant in "${@:-default}"; do
      timeout 280 python3 benchmarks/robots_per_world_kernels.py --model rover --robots 4,8 --total 8192 \
        --seconds 5 --variant "$variant"
    done
  } 2>&1 | quiet | tee "$OUT/kernels.log"
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
