"""diff_drive_controller/DiffDriveController, over every world at once.

cmd_vel (linear.x, angular.z) becomes wheel velocities through `wheel_separation` and
`wheel_radius` (times their multipliers), after the stock speed limiter (`linear.x.*`,
`angular.z.*` velocity and acceleration limits). A world that hears nothing for
`cmd_vel_timeout` seconds gets zero velocity. Odometry integrates the wheel joint
positions (or velocities, with `position_feedback: false`, or the command itself with
`open_loop: true`) as the stock controller does: second-order Runge-Kutta for straight
motion, the exact arc otherwise; its twist is a rolling mean over
`velocity_rolling_window_size` periods.

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

from batchsim.controllers.base import Controller, Params
from batchsim.controllers.topics import ControllerTopics, Input, MessageKind, Output, each_row
from batchsim.model import RobotSpec


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
        self.wheel_command_interface = kind
        self._left_cols = self.claim("left_wheel_names", [f"{j}/{kind}" for j in self.left])
        self._right_cols = self.claim("right_wheel_names", [f"{j}/{kind}" for j in self.right])
        self._pid = kind == "effort"
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
            self._lvel = self.state_columns("left_wheel_names", [f"{j}/velocity" for j in self.left])
            self._rvel = self.state_columns("right_wheel_names", [f"{j}/velocity" for j in self.right])

        W = self.nworld
        self.odom_pose = np.zeros((W, 3))
        self.odom_twist = np.zeros((W, 2))
        self.command_velocity = np.zeros((W, 2))
        self.wheel_velocity = np.zeros((W, 2))
        self._target = np.zeros((W, 2))  # the last cmd_vel of each world
        self._stamp = np.full(W, -np.inf)  # when it arrived (sim time)
        self._last_wheel = np.zeros((W, 2))
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

        Raises ValueError for non-finite values.
        """
        w = self._world(world)
        if not (math.isfinite(linear_x) and math.isfinite(angular_z)):
            raise ValueError(
                f"{self.name}: cmd_vel must be finite, got linear.x={linear_x}, angular.z={angular_z}"
            )
        self._target[w] = (linear_x, angular_z)
        self._stamp[w] = self.time if stamp is None or stamp <= 0 else float(stamp)

    # --- the loop ---
    def _wheels(self, sim: Any) -> np.ndarray:
        state = sim.state
        return np.stack([state[:, self._lpos].mean(axis=1), state[:, self._rpos].mean(axis=1)], axis=1)

    def activate(self, sim: Any, time: float) -> None:
        self._last_wheel[:] = self._wheels(sim)

    def reset(self, sim: Any, worlds: np.ndarray) -> None:
        self.odom_pose[worlds] = 0.0
        self.odom_twist[worlds] = 0.0
        self.command_velocity[worlds] = 0.0
        self._target[worlds] = 0.0
        self._stamp[worlds] = -np.inf
        self._last_wheel[worlds] = self._wheels(sim)[worlds]
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
        wheels = self._wheels(sim)
        if self.open_loop:
            d_lin, d_ang = previous[:, 0] * period, previous[:, 1] * period
        else:
            if self.position_feedback:
                delta = wheels - self._last_wheel
            else:
                delta = wheels * period
            left, right = delta[:, 0] * self.left_radius, delta[:, 1] * self.right_radius
            d_lin = 0.5 * (left + right)
            d_ang = (right - left) / self.wheel_separation
        self._last_wheel = wheels
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

        def cmd_vel(world: int, row: np.ndarray) -> None:
            self.set_cmd_vel(world, float(row[0]), float(row[5]), float(row[6]) if stamped else None)

        def odometry() -> dict[str, np.ndarray]:
            zeros = np.zeros(self.nworld)
            pose, twist = self.odom_pose, self.odom_twist
            return {
                "position": np.stack([pose[:, 0], pose[:, 1], zeros], axis=1),
                "orientation": self.odom_quaternion,
                "linear": np.stack([twist[:, 0], zeros, zeros], axis=1),
                "angular": np.stack([zeros, zeros, twist[:, 1]], axis=1),
            }

        pose_cov, twist_cov = np.zeros(36), np.zeros(36)
        pose_cov[::7] = self.pose_covariance_diagonal
        twist_cov[::7] = self.twist_covariance_diagonal
        kind = MessageKind.TWIST_STAMPED if stamped else MessageKind.TWIST
        return ControllerTopics(
            self.name,
            inputs=(Input(f"{self.name}/cmd_vel", kind, each_row(cmd_vel)),),
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
        )

    @property
    def odom_quaternion(self) -> np.ndarray:
        """(nworld, 4) x, y, z, w of the odometry heading."""
        half = 0.5 * self.odom_pose[:, 2]
        q = np.zeros((self.nworld, 4))
        q[:, 2], q[:, 3] = np.sin(half), np.cos(half)
        return q
