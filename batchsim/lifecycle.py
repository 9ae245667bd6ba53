"""ros2_control's hardware lifecycle, transition for transition as `hardware_interface::System`
drives it: UNKNOWN -> UNCONFIGURED -> INACTIVE -> ACTIVE, FINALIZED; `on_init` ... `on_error`
returning SUCCESS / FAILURE / ERROR.

The table is enforced here, once (`SystemInterface`); an illegal transition raises
`LifecycleError` naming the state. The contract (`batchsim.hardware.BatchedSystem`) is a
SystemInterface.
"""

from __future__ import annotations

import enum


class LifecycleState(enum.IntEnum):
    """Primary lifecycle states, with the ids of lifecycle_msgs/msg/State."""

    UNKNOWN = 0
    UNCONFIGURED = 1
    INACTIVE = 2
    ACTIVE = 3
    FINALIZED = 4


class CallbackReturn(enum.Enum):
    """What a lifecycle callback returns (rclcpp_lifecycle's CallbackReturn)."""

    SUCCESS = "success"
    FAILURE = "failure"
    ERROR = "error"


class LifecycleError(RuntimeError):
    """A lifecycle transition or call that the current state does not allow."""


S = LifecycleState
R = CallbackReturn

# transition -> (states it starts from, callback, outcome -> next state).
# An outcome missing from the table (ERROR, and FAILURE where ros2_control says so) goes
# through error(), as in hardware_interface::System.
_TABLE: dict[str, tuple[frozenset[LifecycleState], str, dict[CallbackReturn, LifecycleState]]] = {
    "configure": (frozenset({S.UNCONFIGURED}), "on_configure", {R.SUCCESS: S.INACTIVE, R.FAILURE: S.UNCONFIGURED}),
    "cleanup": (frozenset({S.INACTIVE}), "on_cleanup", {R.SUCCESS: S.UNCONFIGURED}),
    "activate": (frozenset({S.INACTIVE}), "on_activate", {R.SUCCESS: S.ACTIVE, R.FAILURE: S.INACTIVE}),
    "deactivate": (frozenset({S.ACTIVE}), "on_deactivate", {R.SUCCESS: S.INACTIVE, R.FAILURE: S.ACTIVE}),
    "shutdown": (
        frozenset({S.UNCONFIGURED, S.INACTIVE, S.ACTIVE}),
        "on_shutdown",
        {R.SUCCESS: S.FINALIZED},
    ),
}


class SystemInterface:
    """ros2_control's hardware lifecycle. Subclasses override the `on_*` callbacks.

    Call the transitions (`initialize`, `configure`, `activate`, `deactivate`, `cleanup`,
    `shutdown`, `error`); each runs its callback and moves to the state the callback's
    result selects, and returns that state. A callback that raises counts as ERROR: the
    system goes through `on_error`, then the exception propagates.
    """

    def __init__(self) -> None:
        self._lifecycle = LifecycleState.UNKNOWN

    @property
    def lifecycle_state(self) -> LifecycleState:
        return self._lifecycle

    # --- callbacks (override) ---
    def on_init(self) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_configure(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_cleanup(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_activate(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_deactivate(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_shutdown(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    def on_error(self, previous_state: LifecycleState) -> CallbackReturn:
        return CallbackReturn.SUCCESS

    # --- transitions ---
    def initialize(self) -> LifecycleState:
        """UNKNOWN -> UNCONFIGURED through on_init; FINALIZED if it fails."""
        self._require("initialize", frozenset({S.UNKNOWN}))
        try:
            result = self.on_init()
        except BaseException:
            self._lifecycle = S.FINALIZED
            raise
        self._lifecycle = S.UNCONFIGURED if result is R.SUCCESS else S.FINALIZED
        return self._lifecycle

    def configure(self) -> LifecycleState:
        return self._transition("configure")

    def cleanup(self) -> LifecycleState:
        return self._transition("cleanup")

    def activate(self) -> LifecycleState:
        return self._transition("activate")

    def deactivate(self) -> LifecycleState:
        return self._transition("deactivate")

    def shutdown(self) -> LifecycleState:
        return self._transition("shutdown")

    def error(self) -> LifecycleState:
        """Run on_error: UNCONFIGURED if it handles the error, else FINALIZED."""
        self._require("error", frozenset(set(S) - {S.UNKNOWN, S.FINALIZED}))
        try:
            result = self.on_error(self._lifecycle)
        except BaseException:
            self._lifecycle = S.FINALIZED
            raise
        self._lifecycle = S.UNCONFIGURED if result is R.SUCCESS else S.FINALIZED
        return self._lifecycle

    def _transition(self, name: str) -> LifecycleState:
        allowed, callback, outcomes = _TABLE[name]
        self._require(name, allowed)
        previous = self._lifecycle
        try:
            result = getattr(self, callback)(previous)
        except BaseException:
            self.error()
            raise
        if result in outcomes:
            self._lifecycle = outcomes[result]
        else:
            self.error()
        return self._lifecycle

    def _require(self, what: str, allowed: frozenset[LifecycleState]) -> None:
        if self._lifecycle not in allowed:
            names = " or ".join(sorted(s.name for s in allowed))
            raise LifecycleError(
                f"cannot {what}: the system is {self._lifecycle.name}, and {what} needs {names}"
            )
