"""One recorded world re-stepped with raw MuJoCo: its model with its drawn values, its state set at
each (re)start, and every period's recorded inputs applied as the cpu engine applies them
(batchsim.backends.cpu: ctrl held over the period's steps; a held base velocity written into qvel
before each step; xfrc_applied held). On a cpu recording this is the run itself, to the bit."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence

import mujoco
import numpy as np

from batchsim.plugins.base_velocity import HELD_DOFS, world_velocity
from batchsim.resim.layout import InputsLayout
from batchsim.resim.recorded import WorldRecord

_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
EFFORT_FIELDS = ("qfrc_actuator", "sensordata")  # the fields (StateSource) a joint's effort is read from


@dataclasses.dataclass
class Trajectory:
    """The re-run's state at each period's start: `qpos` (nperiod, nq), `qvel` (nperiod, nv),
    NaN where the world was not running (before its first start, frozen); `since` (nperiod,) the
    sim time of the world's last (re)start, NaN where none. Where asked for, `xpos` (nperiod,
    nbody, 3) and `xquat` (nperiod, nbody, 4): the body poses the system shows at the period's
    start (its last step's kinematics, taken before that step's last substep; a fresh start's
    own), which /tf is made from; NaN where unknown (a start mid-run)."""

    qpos: np.ndarray
    qvel: np.ndarray
    since: np.ndarray
    xpos: np.ndarray | None = None
    xquat: np.ndarray | None = None
    # per joint, the effort the system shows at the period's start (nperiod,): NaN in a
    # (re)start's period (the system shows its reset's, or the step before the recording began),
    # where not running, and where unknown
    effort: dict[str, np.ndarray] | None = None


def with_params(model: mujoco.MjModel, params: dict[str, np.ndarray]) -> mujoco.MjModel:
    """A copy of `model` with one world's drawn values (world_params' fields: model arrays, `opt.*`)."""
    m = copy.copy(model)  # MjModel's copy is a whole new mjModel
    for field, value in params.items():
        if field.startswith("opt."):
            name = field[4:]
            current = getattr(m.opt, name)
            if np.ndim(current) == 0:
                setattr(m.opt, name, type(current)(np.asarray(value).reshape(-1)[0]))
            else:
                current[:] = np.asarray(value).reshape(np.shape(current))
        else:
            getattr(m, field)[:] = value
    return m


def rerun(
    model: mujoco.MjModel, layout: InputsLayout, headers: np.ndarray, world: WorldRecord, poses: bool = False,
    effort: Mapping[str, Sequence] | None = None,
) -> Trajectory:
    """Re-step `world` through every period of `headers` (n, 3: number, time, steps); with
    `poses`, keep the body poses of each period's start too; with `effort` (per joint, where
    the recording says its effort is read from: [field, index, sign]), each joint's effort."""
    n = len(headers)
    qpos, qvel = np.full((n, model.nq), np.nan), np.full((n, model.nv), np.nan)
    since = np.full(n, np.nan)
    xpos = np.full((n, model.nbody, 3), np.nan) if poses else None
    xquat = np.full((n, model.nbody, 4), np.nan) if poses else None
    starts = {s.period: s for s in world.starts}
    number = headers[:, 0].astype(np.int64)
    m, d, running, t0 = model, None, False, np.nan
    qposadr, dofadr = layout.held_base
    held_at = dofadr + np.array(HELD_DOFS) if dofadr >= 0 else None
    sources = {j: (f, int(i), float(sign)) for j, (f, i, sign) in (effort or {}).items() if f in EFFORT_FIELDS}
    efforts = {j: np.full(n, np.nan) for j in sources}
    for k in range(n):
        start = starts.get(int(number[k]))
        if start is not None:
            m = with_params(model, start.params)
            d = mujoco.MjData(m)
            mujoco.mj_setState(m, d, start.state, _INTEGRATION)
            running, t0 = True, float(headers[k, 1])
            if start.fresh:  # a reset's (or the run's first) poses: its own state's kinematics
                mujoco.mj_kinematics(m, d)
        if not running:
            continue
        inputs = layout.split_inputs(world.inputs[k : k + 1])
        if inputs["frozen"][0]:  # the loop holds a frozen world until its reset (its next start)
            running = False
            continue
        qpos[k], qvel[k], since[k] = d.qpos, d.qvel, t0
        if start is None:  # the last step's, as read() shows it
            for j, (f, i, sign) in sources.items():
                efforts[j][k] = sign * getattr(d, f)[i]
        if poses and (start is None or start.fresh):
            xpos[k], xquat[k] = d.xpos, d.xquat
        d.ctrl[:] = inputs["ctrl"][0]
        if layout.nbody:
            d.xfrc_applied[:] = inputs["xfrc_applied"][0]
        held = None
        if held_at is not None and not np.isnan(inputs["base_velocity"][0, 0]):
            held = world_velocity(d.qpos[None, qposadr + 3 : qposadr + 7], inputs["base_velocity"])[0]
        for _ in range(int(headers[k, 2])):
            if held is not None:
                d.qvel[held_at] = held
            mujoco.mj_step(m, d)
    return Trajectory(qpos, qvel, since, xpos, xquat, efforts if sources else None)
