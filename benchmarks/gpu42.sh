#!/usr/bin/env bash
# Issue 42 (the contract owns an engine) on a one-GPU host: the contract's period against raw
# MuJoCo Warp, the new code and the code before the redesign side by side on the same card.
# Three device calls, chained while the machine is warm (it goes cold ~30 s after a call):
#
#   carry [".whl1"]               bash benchmarks/gpu42.sh copy1
#   carry [".whl2"]               bash benchmarks/gpu42.sh copy2
#   carry [".whl3", ".old"]       bash benchmarks/gpu42.sh measure
#
# .old/ is the code before, exported here first (git archive <commit> batchsim benchmarks models
# pyproject.toml setup.py | tar -x -C .old; .git/info/exclude names /.old/). Each side runs
# throughput.py from its own checkout, alternated: new, old, new, old.
source "$(dirname "$0")/gpu_stages.sh"  # $stage, OUT, W, warm; the stages copy1 and copy2
quiet() { grep -v "^Warp \|^Module \|SCHED_FIFO"; }

case $stage in
measure)
  {
    test -d /root/site || bash "$W"/.whl3/install.sh 2>&1 | tail -1  # gpu43.sh's install may have run it
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    echo "== smoke: the warp engine's CUDA paths (graphs, pinned arrays, reset, freeze, device path)"
    timeout 150 python3 - <<'PY'
import numpy as np
import batchsim
sim = batchsim.make("arm", 64, "warp")
sim.configure(); sim.activate()
print("device", sim.device, "nconmax", sim.nconmax)
for _ in range(5):
    sim.command[:] = 0.3; sim.write(); sim.step(10); sim.read()
t = sim.time.copy()
sim.command[3] = np.nan; sim.write(); sim.step(10); sim.read()
assert sim.status[3] & batchsim.Status.BAD_COMMAND and not sim.status[4], sim.status[:6]
sim.reset([1, 2]); sim.read()
assert sim.time[1] == 0 and sim.time[0] > t[0], (sim.time[:3], t[:3])
state = sim.device_state(); host = state.numpy()
assert np.allclose(host[0], sim.state[0], atol=1e-4), (host[0], sim.state[0])
sim.write_device(sim.device_arrays()["ctrl"][:, :6]); sim.step(10); sim.read()
xpos, xquat = sim.body_poses(); assert xpos.shape == (64, sim.model.nbody, 3)
print("smoke ok: BAD_COMMAND, reset, device_state, write_device, body_poses on", sim.device)
sim.shutdown()
PY
    for side in ${SIDES:-new old}; do
      dir=.; [ "$side" = old ] && dir=.old
      echo "== $side"
      (cd "$dir" && PYTHONPATH=/root/site:$PWD timeout 170 python3 benchmarks/throughput.py --backends warp \
        --worlds "${WORLDS:-8192}" --model humanoid --seconds 0.7 --rounds 2 --out "$OUT/$side") | grep -v "^  \|^$"
    done
  } 2>&1 | quiet | tee "$OUT/measure.log"
  ;;
*) echo "unknown stage $stage"; exit 2 ;;
esac
