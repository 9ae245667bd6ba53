"""The loop's side of the simulation services: pause, step, reset to a keyframe with state
overrides, set free joints, apply wrenches (mujoco_ros2_control's `reset_world`, `set_pause`,
`step_simulation`, `set_free_joint_state`, the ExternalWrenchPlugin's `apply_wrench`;
batchsim's `/batchsim/pause` and `step`). No rclpy.

Everything runs in the loop thread (the bridge host's update and idle), between two periods.
A request is validated whole before anything changes, so a bad entry leaves every world as
it was, and is answered with upstream's wording: `Entry 2 ('cube9'): Unknown body name.`
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import mujoco
import numpy as np

from batchsim.contract import Contract
from batchsim.fleet.reset import reset_robot
from batchsim.loop import SimLoop
from batchsim.memory import Memory
from batchsim.model import InitialState, initial_command
from batchsim.model.spec import RobotPart
from batchsim.plugins.external_wrench import ExternalWrench
from ros_bridge.protocol.requests import mark_wrench_done

#: answer(worker, ticket, sim time, ok, message)
Answer = Callable[[int, int, float, bool, str], None]


class RequestError(ValueError):
    """A request that cannot be carried out; the message is the service's answer."""


class SimulationRequests:
    """Pause, steps, state writes and wrenches for the bridge host. An apply_wrench request is
    marked done in `memory` (the bridge's, with the plugin's arrays), then `wake(worker)`."""

    def __init__(
        self,
        sim: Contract,
        loop: SimLoop,
        answer: Answer,
        memory: Memory | None = None,
        wake: Callable[[int], None] | None = None,
    ):
        self.sim = sim
        self.loop = loop
        self.answer = answer
        self.memory = memory
        self.wake = wake
        self._wrenching: list[tuple[int, int, int]] = []  # (worker, ticket, apply_wrench()'s request)
        # (worker, ticket, steps, strict), in order: the first is running, the others wait for it
        self._stepping: list[tuple[int, int, int, bool]] = []

    # --- pause and steps ---
    def pause(self, worker: int, ticket: int, paused: bool) -> None:
        loop = self.loop
        if loop.paused == paused:
            message = f"Simulation is already {'paused' if paused else 'running'}."
        else:
            loop.pause(paused)
            message = f"Simulation {'paused' if paused else 'resumed'}."
            if not paused and loop.pending_steps:
                loop.abort_steps()
                for w, t, _steps, strict in self._stepping:  # a resume interrupts them, as upstream
                    if strict:
                        self.answer(w, t, loop.sim_time, False, "Steps aborted: simulation was resumed while steps were pending.")
                    else:  # /batchsim/step: the period runs anyway
                        self.answer(w, t, loop.sim_time, True, f"stepped to sim time {loop.sim_time:.6f} s")
                self._stepping = []
        self.answer(worker, ticket, loop.sim_time, True, message)

    def step(self, worker: int, ticket: int, nstep: int | None) -> None:
        """`nstep` physics steps (step_simulation), or one control period (None: /batchsim/step)."""
        loop = self.loop
        if not loop.paused:
            self.answer(worker, ticket, loop.sim_time, False, "Cannot step simulation: simulation is not paused.")
            return
        if nstep is not None and nstep < 1:
            self.answer(worker, ticket, loop.sim_time, False, f"Number of steps must be positive, got: {nstep}")
            return
        steps = loop.substeps if nstep is None else nstep
        self._stepping.append((worker, ticket, steps, nstep is not None))
        if len(self._stepping) == 1:
            loop.step_physics(steps)

    def poll(self) -> None:
        """Answer the running step request once the loop ran its steps, then start the next:
        one at a time, exactly its steps each, as upstream's serialized service; mark the
        apply_wrench requests whose wrenches have all run done (every period, and while paused)."""
        if self._wrenching:
            running = self.sim.wrench_running([request for *_, request in self._wrenching])
            for (worker, ticket, _), run in zip(self._wrenching, running, strict=True):
                if not run and self.memory is not None:
                    mark_wrench_done(self.memory, worker, ticket)
                    if self.wake is not None:
                        self.wake(worker)
            self._wrenching = [w for w, run in zip(self._wrenching, running, strict=True) if run]
        while self._stepping and not self.loop.pending_steps:
            w, t, steps, strict = self._stepping.pop(0)
            time = self.loop.sim_time
            message = f"Completed {steps} simulation step(s)." if strict else f"stepped to sim time {time:.6f} s"
            self.answer(w, t, time, True, message)
            if self._stepping:
                self.loop.step_physics(self._stepping[0][2])

    # --- state writes ---
    def reset_world(self, worker: int, ticket: int, world: int, request: dict) -> None:
        """reset_world: the world (-1: all) to its initial state or a keyframe, then the overrides."""
        sim, loop = self.sim, self.loop
        m = sim.model
        try:
            key = _keyframe(m, request.get("keyframe", ""))
            joints = _joint_overrides(m, request.get("joints") or {})
            free = _free_joints(m, request.get("free") or [])
        except RequestError as e:
            self.answer(worker, ticket, loop.sim_time, False, f"{e} Not resetting world.")
            return
        rows = np.arange(sim.nworld) if world < 0 else np.array([world])
        loop.reset(None if world < 0 else rows)  # every participant hears of it
        if key is not None or joints or free:
            qpos, qvel = sim.qstate(rows)
            if key is not None:
                state = InitialState.of_keyframe(m, key, request["keyframe"], bool(np.any(m.key_ctrl[key])))
                qpos[:], qvel[:] = state.qpos, state.qvel
                held = initial_command(dataclasses.replace(sim.spec, initial=state))  # the command holding it
                sim.set_command(np.tile(held, (len(rows), 1)), rows)
            for adr, dof, position, velocity in joints:
                if position is not None:
                    qpos[:, adr] = position
                if velocity is not None:
                    qvel[:, dof] = velocity
            _apply_free(m, qpos, qvel, free)  # frames: the poses after the reset and the joint overrides
            sim.set_qstate(rows, qpos, qvel)
        what = "initial" if key is None else f"'{request['keyframe']}'"
        message = f"Successfully reset the MuJoCo world to the {what} state."
        if joints or free:
            message += f" Applied {len(joints)} joint and {len(free)} free-joint override(s)."
        self.answer(worker, ticket, loop.sim_time, True, message)

    def reset_robot(self, worker: int, ticket: int, world: int, request: dict, forget: Callable[[int, RobotPart], None]) -> None:
        """`<ns>/<robot>/reset`: robot `request["robot"]` (its index among the world's robots) back
        where it starts in `world`, every other robot and world as they are
        (batchsim.fleet.reset); `forget(world, robot)` drops what the bridge and the robot's
        controllers hold for it."""
        sim = self.sim
        robot = sim.spec.robots[int(request["robot"])]
        try:
            reset_robot(sim, robot, [world])
        except ValueError as e:
            self.answer(worker, ticket, self.loop.sim_time, False, str(e))
            return
        forget(world, robot)
        self.answer(worker, ticket, self.loop.sim_time, True, f"reset robot {robot.name}")

    def set_free_joints(self, worker: int, ticket: int, world: int, request: dict) -> None:
        sim = self.sim
        try:
            free = _free_joints(sim.model, request.get("free") or [])
            if sim.frozen[world]:
                raise RequestError("The world is frozen (it diverged or overflowed): reset it first.")
        except RequestError as e:
            self.answer(worker, ticket, self.loop.sim_time, False, str(e))
            return
        rows = np.array([world])
        qpos, qvel = sim.qstate(rows)
        _apply_free(sim.model, qpos, qvel, free)
        sim.set_qstate(rows, qpos, qvel)
        self.answer(worker, ticket, self.loop.sim_time, True, f"Set {len(free)} free joint state(s).")

    def apply_wrench(self, worker: int, ticket: int, world: int, request: dict) -> None:
        """apply_wrench: the request's wrenches in the world from this period on (checked whole
        by the system); answered now, marked done by poll() once the last of them has run."""
        try:
            wrenches = [
                ExternalWrench(e["body"], e["force"], e["torque"], e["point"], e["duration"], e["ramp_down"])
                for e in request["wrenches"]
            ]
            handle = self.sim.apply_wrench(wrenches, [world])
        except ValueError as e:
            self.answer(worker, ticket, self.loop.sim_time, False, str(e))
            return
        self.answer(worker, ticket, self.loop.sim_time, True, f"Applied {len(wrenches)} wrench(es) successfully.")
        self._wrenching.append((worker, ticket, handle))


# --- validation, all of it before anything is written ---
def _keyframe(m: mujoco.MjModel, name: str) -> int | None:
    if not name:
        return None
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, name)
    if key < 0:
        keys = ", ".join(repr(m.key(k).name) for k in range(m.nkey) if m.key(k).name) or "none"
        raise RequestError(f"Failed to apply keyframe: '{name}' (keyframes: {keys}).")
    return key


def _joint_overrides(m: mujoco.MjModel, js: dict) -> list[tuple[int, int, float | None, float | None]]:
    names, position, velocity = js.get("name", []), js.get("position", []), js.get("velocity", [])
    if js.get("effort"):
        raise RequestError("Joint state effort is not supported; leave 'effort' empty.")
    for field, values in (("position", position), ("velocity", velocity)):
        if values and len(values) != len(names):
            raise RequestError(
                f"Joint state '{field}' has {len(values)} entries but 'name' has {len(names)}; "
                "it must be empty or the same length."
            )
    out = []
    for i, name in enumerate(names):
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        if j < 0:
            raise RequestError(f"Entry {i} ('{name}'): Unknown joint name.")
        kind = int(m.jnt_type[j])
        if kind not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            extra = " Free joints are set through 'state_overrides.free_joints' by body name." if kind == 0 else ""
            raise RequestError(f"Entry {i} ('{name}'): Not a single-DOF (hinge or slide) joint.{extra}")
        values = [v[i] if v else None for v in (position, velocity)]
        if any(v is not None and not math.isfinite(v) for v in values):
            raise RequestError(f"Entry {i} ('{name}'): position and velocity must be finite.")
        out.append((int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]), *values))
    return out


def _free_joints(m: mujoco.MjModel, entries: list[dict]) -> list[tuple[int, int, np.ndarray, np.ndarray, int, int]]:
    """Per entry: (qpos address, dof address, pose (7,), twist (6,), pose frame body, twist frame
    body); a frame body of -1 is the world frame."""
    out = []
    for i, e in enumerate(entries):
        name = e.get("name", "")
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name) if name else -1
        if body < 0:
            raise RequestError(f"Entry {i} ('{name}'): Unknown body name.")
        j = int(m.body_jntadr[body])
        if int(m.body_jntnum[body]) < 1 or int(m.jnt_type[j]) != mujoco.mjtJoint.mjJNT_FREE:
            raise RequestError(f"Entry {i} ('{name}'): Body is not driven by a free joint.")
        pose, twist = np.asarray(e["pose"], float), np.asarray(e["twist"], float)
        if not (np.isfinite(pose).all() and np.isfinite(twist).all()):
            raise RequestError(f"Entry {i} ('{name}'): pose and twist must be finite.")
        norm = float(np.linalg.norm(pose[3:]))
        if norm < 1e-9:
            raise RequestError(f"Entry {i} ('{name}'): the orientation is not a unit quaternion.")
        pose[3:] /= norm
        frames = []
        for field in ("pose_frame", "twist_frame"):
            frame = e.get(field, "")
            fb = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, frame) if frame else -1
            if frame and fb < 0:
                label = field.replace("_frame", "")
                raise RequestError(f"Entry {i} ('{name}'): Unknown {label} frame_id body name: '{frame}'.")
            frames.append(fb)
        out.append((int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]), pose, twist, *frames))
    return out


def _apply_free(m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, free: list) -> None:
    """Write free-joint entries into qpos/qvel rows `(n, nq)`, `(n, nv)`. A frame resolves against
    the bodies' poses in the state these rows hold before the entries (their kinematics, on the
    host: the same on every backend), so earlier entries never move a later entry's frame."""
    d = mujoco.MjData(m) if any(pf >= 0 or tf >= 0 for *_, pf, tf in free) else None
    for k in range(len(qpos)):
        if d is not None:
            d.qpos[:] = qpos[k]
            mujoco.mj_kinematics(m, d)
        for adr, dof, pose, twist, pose_frame, twist_frame in free:
            if pose_frame < 0:
                qpos[k, adr : adr + 7] = pose
            else:
                pos, quat = np.zeros(3), np.zeros(4)
                mujoco.mju_mulPose(pos, quat, d.xpos[pose_frame], d.xquat[pose_frame], pose[:3], pose[3:])
                qpos[k, adr : adr + 3], qpos[k, adr + 3 : adr + 7] = pos, quat
            if twist_frame < 0:
                qvel[k, dof : dof + 6] = twist
            else:  # the frame's orientation only, not its velocity (upstream's rule)
                for part in (slice(0, 3), slice(3, 6)):
                    out = np.zeros(3)
                    mujoco.mju_rotVecQuat(out, twist[part], d.xquat[twist_frame])
                    qvel[k, dof + part.start : dof + part.stop] = out
