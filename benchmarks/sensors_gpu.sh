#!/usr/bin/env bash
# Cameras and lidars on a lent GPU host: the benchmark, the sample figure and the sensor
# tests, one stage per call (each fits the 10-minute limit of one command).
#
# Before: the MuJoCo / MJX / MuJoCo Warp wheels installed into /root/site as
# shared/gpu/stage-wheels.sh says, staged with EXTRA_WHEELS="pyopengl" (MuJoCo's EGL
# context needs PyOpenGL; the cpu and mjx backends render through EGL there), and the
# OpenGL loaders carried as .gl (the device README's "headless rendering" paragraph).
# Then, from the project root on the GPU host, with carry [".gl"]:
#
#   bash benchmarks/sensors_gpu.sh warp    # warp: 16..4096 worlds, 64x64 and 320x240, lidar, loop at 1024
#   bash benchmarks/sensors_gpu.sh host    # cpu and mjx (EGL on the GPU): 16..1024 worlds, loop at 16
#   bash benchmarks/sensors_gpu.sh tests   # tests/test_sensors.py on all three backends, and the figure
#   bash benchmarks/sensors_gpu.sh ros     # warp, 1024 worlds, 64x64 RGB-D at 30 Hz, lidar 10 Hz, physics
#                                          # at 100 Hz: the loop without ROS, then with the bridge and 8
#                                          # subscriber processes (needs the ROS wheels too: carry
#                                          # [".gl", ".whlros"], see shared/gpu/stage-ros-wheels.sh)
#
# Results land in $OUT (or benchmarks/out): sensors_<stage>.json and .log.
set -uo pipefail
cd "$(dirname "$0")/.."
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
export PYTHONPATH=/root/site${PYTHONPATH:+:$PYTHONPATH} MUJOCO_GL=egl PYTHONUNBUFFERED=1
out=${OUT:-benchmarks/out}
mkdir -p "$out"
stage=${1:-warp}
case $stage in
  warp)
    python3 benchmarks/sensors.py --backends warp --worlds 16,256,1024,4096 --sizes 64x64,320x240 \
      --seconds 2 --loop 1024 --loop-size 64x64 --camera-rate 30 --lidar-rate 10 \
      --json "$out/sensors_warp.json" 2>&1 | tee "$out/sensors_warp.log"
    ;;
  host)
    python3 benchmarks/sensors.py --backends cpu,mjx --worlds 16,256,1024 --sizes 64x64,320x240 \
      --seconds 2 --max-frames 80000 --loop 16 --loop-size 320x240 --camera-rate 10 --lidar-rate 10 \
      --json "$out/sensors_host.json" 2>&1 | tee "$out/sensors_host.log"
    ;;
  ros)
    if ! python3 -c "import rclpy" 2>/dev/null; then
      python3 -m pip install -q --no-index --no-deps --no-compile .whlros/*.whl
    fi
    python3 benchmarks/sensors.py --backends warp --no-camera --no-lidar --loop 1024 --ros 1024 \
      --loop-size 64x64 --camera-rate 30 --lidar-rate 10 --control-rate 100 --loop-seconds 5 \
      --ros-seconds 10 --subscriber-processes 8 --json "$out/sensors_ros.json" 2>&1 | tee "$out/sensors_ros.log"
    ;;
  tests)
    BATCHSIM_FORCE_BACKENDS=1 python3 -m pytest -q tests/test_sensors.py 2>&1 | tee "$out/sensors_tests.log"
    python3 benchmarks/sensors.py --backends warp --samples "$out/sensors_samples_warp.png"
    ;;
  *)
    echo "usage: $0 warp|host|tests|ros" >&2
    exit 2
    ;;
esac
