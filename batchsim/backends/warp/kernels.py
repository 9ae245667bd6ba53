"""The Warp kernels of a control period: the per-world check, the commands checked and
narrowed into ctrl, the held base velocity, the read() gather, the float64 clock, and the
row copies that resets and restores make.

Every array leads with `nworld` (one thread per world, or per world and column).
"""

from __future__ import annotations

import threading
from typing import Any

import warp as wp

from batchsim.backends.device import FIELD_SHIFT, INDEX_SHIFT, MAX_INDEX
from batchsim.types import Status

# Warp captures and replays graphs on its CPU device through process-wide state: two systems
# doing so from two threads at once (the shards of one fleet on CPU devices) crash the process
CPU_GRAPHS = threading.Lock()


@wp.kernel
def check_worlds(
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    qacc: wp.array2d(dtype=wp.float32),
    overflow: wp.array(dtype=wp.int32),
    overflow_mask: wp.int32,
    maxval: wp.float32,
    code_out: wp.array(dtype=wp.int32),
):
    """code_out[w]: the world's failure code (batchsim.backends.device): DIVERGED with the first
    bad entry of qpos, qvel, qacc (NaN or beyond mjMAXVAL), OVERFLOW if a buffer overflowed."""
    w = wp.tid()
    field = int(0)  # noqa: UP018  (int(): a mutable Warp variable, not a constant)
    index = int(0)  # noqa: UP018
    for i in range(qpos.shape[1]):
        x = qpos[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 1
            index = i
    for i in range(qvel.shape[1]):
        x = qvel[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 2
            index = i
    for i in range(qacc.shape[1]):
        x = qacc[w, i]
        if field == 0 and (wp.isnan(x) or wp.abs(x) > maxval):
            field = 3
            index = i
    code = int(0)  # noqa: UP018
    if field != 0:
        code = int(Status.DIVERGED) | (field << FIELD_SHIFT) | (wp.min(index, MAX_INDEX) << INDEX_SHIFT)
    if (overflow[w] & overflow_mask) != 0:
        code = code | int(Status.OVERFLOW)
    code_out[w] = code


@wp.kernel
def narrow_ctrl(
    host: wp.array2d(dtype=wp.float32),
    parked: wp.array(dtype=wp.int32),
    ctrl: wp.array2d(dtype=wp.float32),
):
    """The host's ctrl (float32, uploaded) into the simulation's; parked worlds get zero."""
    w, j = wp.tid()
    if parked[w] != 0:
        ctrl[w, j] = wp.float32(0.0)
    else:
        ctrl[w, j] = host[w, j]


@wp.kernel
def apply_commands(
    command: wp.array2d(dtype=wp.float64),
    actuator: wp.array(dtype=wp.int32),
    parked: wp.array(dtype=wp.int32),
    limit: wp.float64,
    ctrl_kept: wp.array2d(dtype=wp.float32),
    ctrl: wp.array2d(dtype=wp.float32),
    rejected: wp.array(dtype=wp.bool),
):
    """write()'s check and narrowing on the device, for commands that are plain copies into
    actuators: a world whose row holds NaN, inf or a value beyond `limit` is rejected (as
    the contract's write() rejects it on the host) and keeps its ctrl; the others' values go, as
    float32, into ctrl[w, actuator[j]] and into the kept copy of ctrl the host path uploads
    from. Parked worlds keep their zero ctrl."""
    w = wp.tid()
    bad = int(0)  # noqa: UP018  (int(): a mutable Warp variable, not a constant)
    for j in range(command.shape[1]):
        if not (wp.abs(command[w, j]) < limit):
            bad = 1
    rejected[w] = bad != 0
    if bad == 0:
        for j in range(command.shape[1]):
            x = wp.float32(command[w, j])
            ctrl_kept[w, actuator[j]] = x
            if parked[w] == 0:
                ctrl[w, actuator[j]] = x


@wp.kernel
def rotate_base_velocity(
    qpos: wp.array2d(dtype=wp.float32),
    target: wp.array2d(dtype=wp.float32),
    qposadr: wp.int32,
    held_out: wp.array2d(dtype=wp.float32),
):
    """held_out[w]: the base velocity's target (batchsim.plugins.base_velocity's world_velocity, inlined):
    body-frame vx, vy rotated into the world by the base's quaternion at qpos[w, qposadr + 3:7],
    then wz; a NaN row stays NaN."""
    w = wp.tid()
    qw = qpos[w, qposadr + 3]
    qx = qpos[w, qposadr + 4]
    qy = qpos[w, qposadr + 5]
    qz = qpos[w, qposadr + 6]
    s = wp.float32(2.0) / (qw * qw + qx * qx + qy * qy + qz * qz)
    vx = target[w, 0]
    vy = target[w, 1]
    held_out[w, 0] = (wp.float32(1.0) - s * (qy * qy + qz * qz)) * vx + s * (qx * qy - qw * qz) * vy
    held_out[w, 1] = s * (qx * qy + qw * qz) * vx + (wp.float32(1.0) - s * (qx * qx + qz * qz)) * vy
    held_out[w, 2] = target[w, 2]


@wp.kernel
def hold_base_velocity(held: wp.array2d(dtype=wp.float32), dofadr: wp.int32, qvel: wp.array2d(dtype=wp.float32)):
    """Before a substep: the free joint's qvel at dofadr + HELD_DOFS (0, 1, 5) = held[w], unless NaN."""
    w = wp.tid()
    if not wp.isnan(held[w, 0]):
        qvel[w, dofadr + 0] = held[w, 0]
        qvel[w, dofadr + 1] = held[w, 1]
        qvel[w, dofadr + 5] = held[w, 2]


@wp.kernel
def gather_state(
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    qfrc_actuator: wp.array2d(dtype=wp.float32),
    sensordata: wp.array2d(dtype=wp.float32),
    clock: wp.array(dtype=wp.float64),
    source: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
    nstate: wp.int32,
    state_out: wp.array2d(dtype=wp.float64),
    sensordata_out: wp.array2d(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float64),
):
    """The read() columns, sensordata and time of every world, widened to float64.

    Column c < nstate is read column c, from field source[c] at index[c]; the next
    nsensordata columns are sensordata; the last is the float64 clock.
    """
    w, c = wp.tid()
    if c < nstate:
        s = source[c]
        i = index[c]
        v = wp.float32(0.0)
        if s == 0:
            v = qpos[w, i]
        elif s == 1:
            v = qvel[w, i]
        elif s == 2:
            v = qfrc_actuator[w, i]
        else:
            v = sensordata[w, i]
        state_out[w, c] = wp.float64(v)
    elif c < nstate + sensordata.shape[1]:
        sensordata_out[w, c - nstate] = wp.float64(sensordata[w, c - nstate])
    else:
        time_out[w] = clock[w]


@wp.kernel
def advance_clock(
    dt: wp.float64,
    nstep: wp.int32,
    clock: wp.array(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float32),
):
    """nstep timesteps onto each world's float64 clock, one addition each as mj_step adds them
    (cpu's time to the bit), and MuJoCo Warp's float32 time set from it."""
    w = wp.tid()
    t = clock[w]
    for _ in range(nstep):
        t = t + dt
    clock[w] = t
    time_out[w] = wp.float32(t)


@wp.kernel
def set_rows(mask: wp.array(dtype=wp.bool), row: wp.array(dtype=Any), out: wp.array2d(dtype=Any)):
    """out[w] = row for the masked worlds (float32, vec3 or quat rows)."""
    w, j = wp.tid()
    if mask[w]:
        out[w, j] = row[j]


@wp.kernel
def set_clock(
    mask: wp.array(dtype=wp.bool),
    value: wp.float64,
    clock: wp.array(dtype=wp.float64),
    time_out: wp.array(dtype=wp.float32),
):
    w = wp.tid()
    if mask[w]:
        clock[w] = value
        time_out[w] = wp.float32(value)


@wp.kernel
def gather_poses(
    worlds: wp.array(dtype=wp.int32),
    xpos: wp.array2d(dtype=wp.vec3),
    xquat: wp.array2d(dtype=wp.quat),
    poses_out: wp.array3d(dtype=wp.float32),
):
    """poses_out[i, body] = xpos (3), then xquat (4, MuJoCo's order: w, x, y, z) of world worlds[i]."""
    i, body = wp.tid()
    w = worlds[i]
    p = xpos[w, body]
    q = xquat[w, body]
    for k in range(3):
        poses_out[i, body, k] = p[k]
    for k in range(4):
        poses_out[i, body, 3 + k] = q[k]


@wp.kernel
def copy_rows(mask: wp.array(dtype=wp.bool), src: wp.array2d(dtype=Any), out: wp.array2d(dtype=Any)):
    w, j = wp.tid()
    if mask[w]:
        out[w, j] = src[w, j]


@wp.kernel
def copy_items(mask: wp.array(dtype=wp.bool), src: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    w = wp.tid()
    if mask[w]:
        out[w] = src[w]
