"""diff_drive_controller/DiffDriveController, over every world at once.

cmd_vel (linear.x, angular.z) becomes wheel velocities through `wheel_separation` and
`wheel_radius` (times their multipliers), after the stock speed limiter (`linear.x.*`,
`angular.z.*` velocity and acceleration limits). A world that hears nothing for
`cmd_vel_timeout` seconds gets zero velocity. Odometry integrates the wheel joint
positions (or velocities, with `position_feedback: false`, or the command itself with
`open_loop: true`) as the stock controller does: second-order Runge-Kutta for straight
motion, the exact arc otherwise; its twist is a rolling mean over
`velocity_rolling_window_size` periods. Everything it accumulates is float64.

Wheel positions from a float32 backend (mjx, warp) lose resolution as the wheel turns: at
1e4 rad a float32 angle moves in steps of ~1e-3 rad, a percent of a period's travel, and
the device's own float32 integration of it drifts. When both readings of a wheel are
exactly float32 values (as every reading of those backends is, and a float64 reading
almost never is), its travel over the period is the trapezoid of its two velocity
readings instead, which float32 resolves to ~1e-7 of the speed at any angle; float64
positions (the cpu backend) are differenced as upstream does.

Wheels are driven through their `velocity` command interfaces, as in ros2_control. A
model whose wheels only have `effort` interfaces (batchsim's car: torque motors) is
driven by a per-wheel velocity PI loop inside the controller, with the batchsim
parameters `wheel_velocity_pid.p`, `.i` and `.i_clamp`; `wheel_command_interface`
(velocity or effort) picks one when a wheel has both.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from batchsim.controllers.base import Controller, Params, last_per_world
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Output, Transform
from batchsim.model import InterfaceKind, RobotSpec
from batchsim.types import MAX_COMMAND


class _Limiter:
    """The stock SpeedLimiter's velocity and acceleration limits for one axis (NaN: none)."""

    def __init__(self, params: Params, axis: str):
        def limit(name: str, flag: str) -> float:
            value = params.number(f"{axis}.{name}", math.nan, allow_nan=True)
            # older configs switch a limit on with has_*_limits; a limit given without it counts
            if params.has(f"{axis}.{flag}") and not params.boolean(f"{axis}.{flag}"):
                return math.nan
            return value

        self.max_v = limit("max_velocity", "has_velocity_limits")
        self.min_v = limit("min_velocity", "has_velocity_limits")
        self.max_a = limit("max_acceleration", "has_acceleration_limits")
        self.min_a = limit("min_acceleration", "has_acceleration_limits")
        for name in (
            "max_jerk",
            "min_jerk",
            "has_jerk_limits",
            "max_deceleration",
            "min_deceleration",
            "max_acceleration_reverse",
            "max_deceleration_reverse",
        ):
            params.raw(f"{axis}.{name}", None)
        if math.isnan(self.min_v) and not math.isnan(self.max_v):
            self.min_v = -self.max_v  # stock: an unspecified min_* is -max_*
        if math.isnan(self.min_a) and not math.isnan(self.max_a):
            self.min_a = -self.max_a

    def limit(self, v: np.ndarray, previous: np.ndarray, dt: float) -> np.ndarray:
        if not math.isnan(self.max_a) and dt > 0:
            v = np.clip(v, previous + self.min_a * dt, previous + self.max_a * dt)
        return self.limit_velocity(v)

    def limit_velocity(self, v: np.ndarray) -> np.ndarray:
        if not math.isnan(self.max_v):
            v = np.clip(v, self.min_v, self.max_v)
        return v


class DiffDriveController(Controller):
    """diff_drive_controller/DiffDriveController.

    Parameters (stock): `left_wheel_names`, `right_wheel_names`, `wheel_separation`,
    `wheel_radius`, `wheel_separation_multiplier`, `left_wheel_radius_multiplier`,
    `right_wheel_radius_multiplier`, `cmd_vel_timeout`, `open_loop`, `position_feedback`,
    `velocity_rolling_window_size`, `odom_frame_id`, `base_frame_id`,
    `pose_covariance_diagonal`, `twist_covariance_diagonal`, `enable_odom_tf`,
    `use_stamped_vel`, `publish_rate`, `linear.x.*` and `angular.z.*` limits.

    Attributes:
      odom_pose: (nworld, 3) x, y, yaw in the odom frame, from wheel odometry.
      odom_twist: (nworld, 2) linear x and angular z velocity, rolling mean.
      command_velocity: (nworld, 2) the limited linear x, angular z being executed.
      wheel_velocity: (nworld, 2) left and right wheel speed targets, rad/s.
    """

    TYPE: ClassVar[str] = "diff_drive_controller/DiffDriveController"
    ACCEPTED = (
        *Controller.ACCEPTED,
        "publish_limited_velocity",
        "publish_cmd",
        "publish_wheel_data",
        "preserve_turning_radius",
        "wheels_per_side",
        "tf_frame_prefix_enable",
        "tf_frame_prefix",
        "publish_rate",
    )

    def __init__(self, name: str, params: Params, spec: RobotSpec, nworld: int):
        super().__init__(name, params, spec, nworld)
        self.left = params.string_list("left_wheel_names", nonempty=True)
        self.right = params.string_list("right_wheel_names", nonempty=True)
        self.check_joints("left_wheel_names", self.left)
        self.check_joints("right_wheel_names", self.right)
        both = set(self.left) & set(self.right)
        if both:
            raise params.error("right_wheel_names", f"{sorted(both)[0]!r} is also a left wheel")
        self.wheel_separation = params.number("wheel_separation", positive=True) * params.number(
            "wheel_separation_multiplier", 1.0, positive=True
        )
        radius = params.number("wheel_radius", positive=True)
        self.left_radius = radius * params.number("left_wheel_radius_multiplier", 1.0, positive=True)
        self.right_radius = radius * params.number("right_wheel_radius_multiplier", 1.0, positive=True)
        self.cmd_vel_timeout = params.number("cmd_vel_timeout", 0.5, minimum=0.0)
        self.open_loop = params.boolean("open_loop", False)
        self.position_feedback = params.boolean("position_feedback", True)
        self.window = int(params.number("velocity_rolling_window_size", 10, minimum=1))
        self.odom_frame_id = params.string("odom_frame_id", "odom")
        self.base_frame_id = params.string("base_frame_id", "base_link")
        self.enable_odom_tf = params.boolean("enable_odom_tf", True)
        self.use_stamped_vel = params.boolean("use_stamped_vel", True)
        self.pose_covariance_diagonal = self._diagonal(params, "pose_covariance_diagonal")
        self.twist_covariance_diagonal = self._diagonal(params, "twist_covariance_diagonal")
        self.linear = _Limiter(params, "linear.x")
        self.angular = _Limiter(params, "angular.z")

        wheels = self.left + self.right
        served = {c.rsplit("/", 1)[1] for c in self._command_names if c.rsplit("/", 1)[0] in wheels}
        kind = params.choice(
            "wheel_command_interface",
            ("velocity", "effort"),
            "velocity" if "velocity" in served or "effort" not in served else "effort",
        )
        self.wheel_command_interface = InterfaceKind(kind)
        self._left_cols = self.claim("left_wheel_names", [f"{j}/{kind}" for j in self.left])
        self._right_cols = self.claim("right_wheel_names", [f"{j}/{kind}" for j in self.right])
        self._pid = self.wheel_command_interface is InterfaceKind.EFFORT
        self.kp = params.number("wheel_velocity_pid.p", 0.1, minimum=0.0)
        self.ki = params.number("wheel_velocity_pid.i", 1.0, minimum=0.0)
        self.i_clamp = params.number("wheel_velocity_pid.i_clamp", 2.0, minimum=0.0)
        feedback = "position" if self.position_feedback else "velocity"
        self._lpos = self.state_columns("left_wheel_names", [f"{j}/{feedback}" for j in self.left])
        self._rpos = self.state_columns("right_wheel_names", [f"{j}/{feedback}" for j in self.right])
        if self._pid:
            m = spec.mjmodel
            acts = [spec.commands[c].actuator_id for c in np.concatenate([self._left_cols, self._right_cols])]
            limited = m.actuator_ctrllimited[acts].astype(bool)
            self._effort_min = np.where(limited, m.actuator_ctrlrange[acts, 0], -np.inf)
            self._effort_max = np.where(limited, m.actuator_ctrlrange[acts, 1], np.inf)
        # wheel speeds: the PI loop's feedback, and the odometry's on float32 positions
        self._lvel = self._rvel = None
        if self._pid or all(f"{j}/velocity" in self._state_names for j in wheels):
            self._lvel = self.state_columns("left_wheel_names", [f"{j}/velocity" for j in self.left])
            self._rvel = self.state_columns("right_wheel_names", [f"{j}/velocity" for j in self.right])

        W = self.nworld
        self.odom_pose = np.zeros((W, 3))
        self.odom_twist = np.zeros((W, 2))
        self.command_velocity = np.zeros((W, 2))
        self.wheel_velocity = np.zeros((W, 2))
        self._target = np.zeros((W, 2))  # the last cmd_vel of each world
        self._stamp = np.full(W, -np.inf)  # when it arrived (sim time)
        self._last_wheel = np.zeros((W, 2))  # float64, like everything accumulated here
        self._last_speed = np.zeros((W, 2))
        self._last_coarse = np.zeros((W, 2), bool)  # the last position reading was a float32 value
        self._ring = np.zeros((2, W, self.window))  # linear, angular increments / dt
        self._ring_n = 0
        self._i_term = np.zeros((W, len(self.left) + len(self.right)))

    @staticmethod
    def _diagonal(params: Params, key: str) -> list[float]:
        value = params.raw(key, [0.0] * 6)
        if (
            not isinstance(value, list)
            or len(value) != 6
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        ):
            raise params.error(key, f"must be a list of 6 numbers, got {value!r}")
        return [float(v) for v in value]

    # --- input ---
    def set_cmd_vel(self, world: int, linear_x: float, angular_z: float, stamp: float | None = None) -> None:
        """One world's cmd_vel (Twist linear.x, angular.z); `stamp` in sim time, None: now.

        The one-world convenience over `set_cmd_vel_batch`; raises ValueError where it rejects.
        """
        self._world(world)
        row = [linear_x, angular_z] if stamp is None else [linear_x, angular_z, stamp]
        rejected = self.set_cmd_vel_batch([world], np.array([row], dtype=np.float64))
        if rejected:
            raise ValueError(rejected[0][1])

    def set_cmd_vel_batch(self, worlds: Any, rows: Any) -> list[tuple[int, str]]:
        """The cmd_vel of several worlds at once; a later row for a world wins.

        Args:
          worlds: (n,) int, the world of each row.
          rows: (n, 2) float64 linear.x, angular.z (Twist), or (n, 3) with the header stamp
            in sim seconds as the third column (TwistStamped; 0 or less: now).

        Returns:
          (index, reason) for each rejected row: a world out of range, a NaN or inf, or a
          velocity whose wheel speeds would reach MAX_COMMAND (1e10), which write() would
          refuse. Those worlds keep their previous cmd_vel. Never raises for a bad row.

        Raises:
          ValueError: rows is not (n, 2) or (n, 3) for n worlds (the caller's bug).
        """
        w, rejected = self._batch_worlds(worlds)
        values = np.asarray(rows, dtype=np.float64)
        if values.ndim != 2 or values.shape[1] not in (2, 3) or len(values) != len(w):
            raise ValueError(
                f"{self.name}: cmd_vel rows must be ({len(w)}, 2) or ({len(w)}, 3), got {values.shape}"
            )
        lin, ang = values[:, 0], values[:, 1]
        stamp = values[:, 2] if values.shape[1] == 3 else np.zeros(len(w))
        with np.errstate(invalid="ignore", over="ignore"):
            finite = np.isfinite(lin) & np.isfinite(ang)
            half = 0.5 * self.wheel_separation
            speed = (
                np.abs(self.linear.limit_velocity(lin)) + np.abs(self.angular.limit_velocity(ang)) * half
            ) / min(self.left_radius, self.right_radius)
            fast = ~(speed < MAX_COMMAND)
        for k in np.flatnonzero(~finite | fast | ~np.isfinite(stamp)).tolist():
            if k in rejected:
                continue
            if not finite[k]:
                reason = f"cmd_vel must be finite, got linear.x={lin[k]}, angular.z={ang[k]}"
            elif fast[k]:
                reason = (
                    f"cmd_vel linear.x={lin[k]:g}, angular.z={ang[k]:g} would turn the wheels at "
                    f"{speed[k]:.3g} rad/s, beyond the {MAX_COMMAND:g} write() accepts"
                )
            else:
                reason = f"cmd_vel stamp must be finite, got {stamp[k]}"
            rejected[k] = f"{self.name}: {reason}"
        good = np.ones(len(w), bool)
        good[list(rejected)] = False
        good = np.flatnonzero(good)
        keep = good[last_per_world(w[good])]
        self._target[w[keep], 0] = lin[keep]
        self._target[w[keep], 1] = ang[keep]
        self._stamp[w[keep]] = np.where(stamp[keep] > 0, stamp[keep], self.time)
        return sorted(rejected.items())

    # --- the loop ---
    def _wheels(self, sim: Any) -> np.ndarray:
        """(nworld, 2) left and right wheel positions (velocities with position_feedback: false)."""
        state = sim.state
        return np.stack([state[:, self._lpos].mean(axis=1), state[:, self._rpos].mean(axis=1)], axis=1)

    def _speeds(self, sim: Any) -> np.ndarray:
        """(nworld, 2) left and right wheel velocities."""
        state = sim.state
        return np.stack([state[:, self._lvel].mean(axis=1), state[:, self._rvel].mean(axis=1)], axis=1)

    def _coarse(self, sim: Any) -> np.ndarray:
        """(nworld, 2): every position reading of that side is a float32 value (a float32 backend's)."""
        state = sim.state
        return np.stack(
            [_is_float32(state[:, self._lpos]).all(axis=1), _is_float32(state[:, self._rpos]).all(axis=1)],
            axis=1,
        )

    def _remember(self, sim: Any, worlds: Any) -> None:
        """Take the current wheel readings of `worlds` as the ones the next period differences."""
        self._last_wheel[worlds] = self._wheels(sim)[worlds]
        # the next update differences this very reading (no time passes): positions say 0
        self._last_coarse[worlds] = False

    def activate(self, sim: Any, time: float) -> None:
        self._remember(sim, slice(None))

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.odom_pose[worlds] = 0.0
        self.odom_twist[worlds] = 0.0
        self.command_velocity[worlds] = 0.0
        self._target[worlds] = 0.0
        self._stamp[worlds] = -np.inf
        self._remember(sim, worlds)
        self._ring[:, worlds] = 0.0
        self._i_term[worlds] = 0.0

    def update(self, sim: Any, time: float, period: float) -> None:
        # command: timeout, then the speed limiter
        target = np.where((time - self._stamp <= self.cmd_vel_timeout)[:, None], self._target, 0.0)
        previous = self.command_velocity
        lin = self.linear.limit(target[:, 0], previous[:, 0], period)
        ang = self.angular.limit(target[:, 1], previous[:, 1], period)
        self.command_velocity = np.stack([lin, ang], axis=1)

        # odometry
        if self.open_loop:
            d_lin, d_ang = previous[:, 0] * period, previous[:, 1] * period
            self._last_wheel[:] = self._wheels(sim)
        else:
            delta = self._travel(sim, period)
            left, right = delta[:, 0] * self.left_radius, delta[:, 1] * self.right_radius
            d_lin = 0.5 * (left + right)
            d_ang = (right - left) / self.wheel_separation
        self._integrate(d_lin, d_ang)
        if period > 0:
            slot = self._ring_n % self.window
            self._ring[0, :, slot] = d_lin / period
            self._ring[1, :, slot] = d_ang / period
            self._ring_n += 1
            n = min(self._ring_n, self.window)
            self.odom_twist[:] = self._ring[:, :, :n].mean(axis=2).T

        # wheel speeds
        half = 0.5 * self.wheel_separation
        wl = (lin - ang * half) / self.left_radius
        wr = (lin + ang * half) / self.right_radius
        self.wheel_velocity[:, 0], self.wheel_velocity[:, 1] = wl, wr
        if not self._pid:
            sim.command[:, self._left_cols] = wl[:, None]
            sim.command[:, self._right_cols] = wr[:, None]
            return
        state = sim.state
        nl = len(self.left)
        measured = np.concatenate([state[:, self._lvel], state[:, self._rvel]], axis=1)
        wanted = np.concatenate(
            [np.repeat(wl[:, None], nl, axis=1), np.repeat(wr[:, None], len(self.right), axis=1)], axis=1
        )
        error = wanted - measured
        i_term = np.clip(self._i_term + self.ki * error * period, -self.i_clamp, self.i_clamp)
        effort = self.kp * error + i_term
        limited = np.clip(effort, self._effort_min, self._effort_max)
        # anti-windup: the integral only grows while the motor is not saturated
        self._i_term = np.where(limited == effort, i_term, self._i_term)
        effort = limited
        sim.command[:, self._left_cols] = effort[:, :nl]
        sim.command[:, self._right_cols] = effort[:, nl:]

    def _travel(self, sim: Any, period: float) -> np.ndarray:
        """(nworld, 2) float64 radians each side's wheels turned in the last period."""
        wheels = self._wheels(sim)
        if not self.position_feedback:
            self._last_wheel[:] = wheels
            return wheels * period
        delta = wheels - self._last_wheel
        self._last_wheel[:] = wheels
        if self._lvel is not None:
            speeds, coarse = self._speeds(sim), self._coarse(sim)
            quantized = coarse & self._last_coarse
            if quantized.any():  # float32 positions: the speeds' trapezoid resolves the travel
                delta = np.where(quantized, 0.5 * (speeds + self._last_speed) * period, delta)
            self._last_speed[:] = speeds
            self._last_coarse[:] = coarse
        return delta

    def _integrate(self, d_lin: np.ndarray, d_ang: np.ndarray) -> None:
        """The stock Odometry::integrate: Runge-Kutta 2 for small turns, the exact arc otherwise."""
        x, y, yaw = self.odom_pose[:, 0], self.odom_pose[:, 1], self.odom_pose[:, 2]
        straight = np.abs(d_ang) < 1e-6
        mid = yaw + 0.5 * d_ang
        new_yaw = yaw + d_ang
        safe = np.where(straight, 1.0, d_ang)
        r = d_lin / safe
        dx = np.where(straight, d_lin * np.cos(mid), r * (np.sin(new_yaw) - np.sin(yaw)))
        dy = np.where(straight, d_lin * np.sin(mid), -r * (np.cos(new_yaw) - np.cos(yaw)))
        self.odom_pose[:, 0] = x + dx
        self.odom_pose[:, 1] = y + dy
        self.odom_pose[:, 2] = new_yaw

    def topics(self) -> ControllerTopics:
        """`<ns>/<controller>/cmd_vel` (TwistStamped; Twist with use_stamped_vel false) and
        `<ns>/<controller>/odom` (nav_msgs/Odometry in odom_frame_id, twist in base_frame_id)."""
        stamped = self.use_stamped_vel
        columns = [0, 5, 6] if stamped else [0, 5]  # linear.x, angular.z (, the stamp)

        def cmd_vel(worlds: np.ndarray, rows: np.ndarray) -> list[tuple[int, str]]:
            return self.set_cmd_vel_batch(worlds, rows[:, columns])

        def odometry() -> dict[str, np.ndarray]:
            zeros = np.zeros(self.nworld)
            pose, twist = self.odom_pose, self.odom_twist
            return {
                "position": np.stack([pose[:, 0], pose[:, 1], zeros], axis=1),
                "orientation": self.odom_quaternion,
                "linear": np.stack([twist[:, 0], zeros, zeros], axis=1),
                "angular": np.stack([zeros, zeros, twist[:, 1]], axis=1),
            }

        def odom_transform() -> np.ndarray:  # enable_odom_tf: odom -> base_link on tf
            pose = self.odom_pose
            return np.concatenate([pose[:, :2], np.zeros((self.nworld, 1)), self.odom_quaternion], axis=1)

        transforms = (Transform(self.odom_frame_id, self.base_frame_id, odom_transform),) if self.enable_odom_tf else ()
        pose_cov, twist_cov = np.zeros(36), np.zeros(36)
        pose_cov[::7] = self.pose_covariance_diagonal
        twist_cov[::7] = self.twist_covariance_diagonal
        kind = MessageKind.TWIST_STAMPED if stamped else MessageKind.TWIST
        return ControllerTopics(
            self.name,
            inputs=(Input(f"{self.name}/cmd_vel", kind, cmd_vel),),
            outputs=(
                Output(
                    f"{self.name}/odom",
                    MessageKind.ODOMETRY,
                    odometry,
                    frame_id=self.odom_frame_id,
                    child_frame_id=self.base_frame_id,
                    covariance={"pose": tuple(pose_cov), "twist": tuple(twist_cov)},
                ),
            ),
            transforms=transforms,
        )

    @property
    def odom_quaternion(self) -> np.ndarray:
        """(nworld, 4) x, y, z, w of the odometry heading."""
        half = 0.5 * self.odom_pose[:, 2]
        q = np.zeros((self.nworld, 4))
        q[:, 2], q[:, 3] = np.sin(half), np.cos(half)
        return q


def _is_float32(x: np.ndarray) -> np.ndarray:
    """Elementwise: x is exactly a float32 value (NaN: False)."""
    return x.astype(np.float32).astype(np.float64) == x
