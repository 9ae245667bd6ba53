#!/usr/bin/env bash
# Cameras and lidars on a lent GPU host: the benchmark, the sample figure and the sensor
# tests, one stage per call (each fits the 10-minute limit of one command; warp and host
# took under 6 minutes in the estimate below).
#
# Before: the MuJoCo / MJX / MuJoCo Warp wheels installed into /root/site as
# shared/gpu/stage-wheels.sh says, staged with EXTRA_WHEELS="pyopengl" (MuJoCo's EGL
# context needs PyOpenGL; the cpu and mjx backends render through EGL there), and the
# OpenGL loaders carried as .gl (the device README's "headless rendering" paragraph).
# Then, from the project root on the GPU host, with carry [".gl"]:
#
#   bash benchmarks/sensors_gpu.sh warp    # warp: 16..4096 worlds, 64x64 and 320x240, lidar (host and
#                                          # device), the loop at 1024; raw launches and raw graphs beside
#   bash benchmarks/sensors_gpu.sh host    # cpu and mjx (EGL on the GPU): 16..1024 worlds, the loop at 16
#                                          # worlds with a 320x240 camera at 10 Hz (the 2-core target's)
#   bash benchmarks/sensors_gpu.sh tests   # tests/test_sensors.py on all three backends, and the figure
#   bash benchmarks/sensors_gpu.sh ros     # warp, 1024 worlds, 64x64 RGB-D at 30 Hz, lidar 10 Hz, physics
#                                          # at 100 Hz: the loop without ROS, then with the bridge and 8
#                                          # subscriber processes (needs the ROS wheels too: carry
#                                          # [".gl", ".whlros"], see shared/gpu/stage-ros-wheels.sh)
#
# `bash benchmarks/sensors_gpu.sh STAGE --smoke` runs the same commands at toy sizes (a few
# worlds, 16x16 images, a fraction of a second each): what a CPU-only machine runs to check
# a stage before a GPU call is spent on it (PATH must give the project's python3 there).
#
# Results land in $OUT (or benchmarks/out): sensors_<stage>.json and .log, nothing else (a
# call brings back 8 files at most). JAX's compile cache goes to /tmp/batchsim-jax-cache,
# so that mjx compiles once per world count, not once per row.
set -uo pipefail
cd "$(dirname "$0")/.."
if [ -d .gl ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
fi
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
export PYTHONPATH=/root/site${PYTHONPATH:+:$PYTHONPATH} MUJOCO_GL=egl PYTHONUNBUFFERED=1
out=${OUT:-benchmarks/out}
mkdir -p "$out"
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-/tmp/batchsim-jax-cache}
stage=${1:-warp}
smoke=${2:-}
if [ "$smoke" = "--smoke" ]; then
  # toy sizes, same code paths
  big="--worlds 2,4 --sizes 16x16,32x24 --seconds 0.2"
  wide="$big"
  host_loop="--loop 4 --loop-size 32x24 --loop-seconds 0.3"
  warp_loop="--loop 4 --loop-size 16x16 --loop-seconds 0.3"
  ros="--loop 4 --ros 4 --loop-size 16x16 --loop-seconds 0.3 --ros-seconds 2 --subscriber-processes 2"
  tag=_smoke
elif [ -n "$smoke" ]; then
  echo "usage: $0 warp|host|tests|ros [--smoke]" >&2
  exit 2
else
  big="--worlds 16,256,1024,4096 --sizes 64x64,320x240 --seconds 2"
  wide="--worlds 16,256,1024 --sizes 64x64,320x240 --seconds 2 --max-frames 80000"
  host_loop="--loop 16 --loop-size 320x240 --loop-seconds 5"
  warp_loop="--loop 1024 --loop-size 64x64 --loop-seconds 3"
  ros="--loop 1024 --ros 1024 --loop-size 64x64 --loop-seconds 5 --ros-seconds 10 --subscriber-processes 8"
  tag=
fi
case $stage in
  warp)
    # shellcheck disable=SC2086
    python3 benchmarks/sensors.py --backends warp $big $warp_loop --camera-rate 30 --lidar-rate 10 \
      --json "$out/sensors_warp$tag.json" 2>&1 | tee "$out/sensors_warp$tag.log"
    ;;
  host)
    # shellcheck disable=SC2086
    python3 benchmarks/sensors.py --backends cpu,mjx $wide $host_loop --camera-rate 10 --lidar-rate 10 \
      --json "$out/sensors_host$tag.json" 2>&1 | tee "$out/sensors_host$tag.log"
    ;;
  ros)
    if ! python3 -c "import rclpy" 2>/dev/null; then
      python3 -m pip install -q --no-index --no-deps --no-compile .whlros/*.whl
    fi
    # shellcheck disable=SC2086
    python3 benchmarks/sensors.py --backends warp --no-camera --no-lidar $ros --camera-rate 30 \
      --lidar-rate 10 --control-rate 100 --json "$out/sensors_ros$tag.json" 2>&1 | tee "$out/sensors_ros$tag.log"
    ;;
  tests)
    BATCHSIM_FORCE_BACKENDS=1 python3 -m pytest -q tests/test_sensors.py 2>&1 | tee "$out/sensors_tests$tag.log"
    python3 benchmarks/sensors.py --backends warp --samples "$out/sensors_samples_warp$tag.png"
    ;;
  *)
    echo "usage: $0 warp|host|tests|ros [--smoke]" >&2
    exit 2
    ;;
esac
