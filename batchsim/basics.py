"""The project's plain building blocks that need nothing but Python: enums named by strings in any
case (AnyCase) and the two errors a user's value raises. batchsim/types.py re-exports them; the
command line's parser and ros_bridge/options.py import them from here, before NumPy loads."""

from __future__ import annotations

from typing import Any


class AnyCase:
    """Mixed into an Enum before its base (`class Mode(AnyCase, enum.Enum)`): a string names a
    member in any case, by its value or its name, as MJX's `Impl` does; strings come in at the
    edges (YAML, flags, ROS requests) and become members at once."""

    @classmethod
    def _missing_(cls, value: object) -> Any:
        if isinstance(value, str):
            key = value.lower()
            for member in cls:  # type: ignore[attr-defined]
                if member.name.lower() == key or (isinstance(member.value, str) and member.value.lower() == key):
                    return member
        return None


class OptionError(ValueError):
    """A bad option value. `option` is its Python name (`control_rate`); str() reads
    `"<option> <detail>"`, and `named(flag)` the same with the command line's name for it.
    An empty `option` is a problem of no single option: the message is the detail alone."""

    def __init__(self, option: str, detail: str):
        super().__init__(f"{option} {detail}" if option else detail)
        self.option = option
        self.detail = detail

    def named(self, name: str) -> str:
        return f"{name} {self.detail}" if self.option else self.detail


class ConfigurationError(ValueError):
    """The model or its ros2_control block asks for something the simulation cannot serve."""
