"""A robot's view of a world of several (batchsim.fleet): the world's spec as that robot names it."""

from __future__ import annotations

import dataclasses

from batchsim.model.spec import RobotPart, RobotSpec

#: what the other robots' interfaces are called in a robot's view: no name a YAML gives
#: (`b/joint1`) reaches them, so a robot's controllers can never claim or read another's
OTHER = "(another robot's) "


def robot_view(world: RobotSpec, robot: RobotPart) -> RobotSpec:
    """The world's spec as `robot` names it: its joints, sensors and floating base only, with
    their local names; the state and command lists whole, in the world's order (so columns are
    the world's), the robot's own entries with local names and the others' behind OTHER."""

    def own(name: str | None) -> bool:
        return bool(name) and name.startswith(robot.prefix)

    def local(name: str | None) -> str | None:
        return robot.local(name) if name and own(name) else name

    base = robot.floating_base
    return dataclasses.replace(
        world,
        joints=[dataclasses.replace(j, name=robot.local(j.name)) for j in world.joints if own(j.name)],
        state=[dataclasses.replace(c, name=local(c.name) if own(c.name) else OTHER + c.name) for c in world.state],
        commands=[
            dataclasses.replace(c, name=local(c.name), actuator=local(c.actuator), joint=local(c.joint))
            if own(c.name)
            else dataclasses.replace(c, name=OTHER + c.name)
            for c in world.commands
        ],
        sensors=[
            dataclasses.replace(s, name=robot.local(s.name), objname=local(s.objname))
            for s in world.sensors
            if own(s.name)
        ],
        floating_base=None
        if base is None
        else dataclasses.replace(base, joint=robot.local(base.joint), body=robot.local(base.body)),
        robots=[],
    )
