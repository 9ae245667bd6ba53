# Sourced by the GPU session scripts (gpu24.sh, gpu27.sh): what every stage needs, and the
# stages that only bring the staged wheels in (copy1, copy2). After it, $stage is the stage
# asked for and "$@" its arguments; OUT is where the logs go; W the folder holding the staged
# .whl*/ folders (WHEELS, default: here).
set -uo pipefail
stage=${1:?stage}
shift || true
export PYTHONPATH=/root/site:$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
W=${WHEELS:-.}
mkdir -p "$OUT"
# the wheels come in two calls (a call carries at most 64 MiB); the machine stays warm 30 s
case $stage in
copy1) mkdir -p /root/stage && cp "$W"/.whl1/* /root/stage/ && echo copied .whl1; exit ;;
copy2) cp "$W"/.whl2/* /root/stage/ && echo copied .whl2; exit ;;
esac
warm() { test -d /root/site || { echo "COLD: the machine was given back; start again at copy1"; exit 3; }; }
