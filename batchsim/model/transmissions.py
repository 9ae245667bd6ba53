"""ros2_control `<transmission>`s of a description, as mujoco_ros2_control runs them.

A transmission puts ros2_control joints on one side and actuators on the other. An actuator
is named as mujoco_ros2_control resolves it: a MuJoCo joint that an actuator drives, else an
actuator's own name (a tendon actuator named after its joint). The joints need not exist in
the MJCF: `joint1` of the URDF may be moved by MuJoCo joints `actuator1` and `actuator2`.

    <transmission name="arm_trans">
      <plugin>transmission_interface/DifferentialTransmission</plugin>
      <joint name="joint1" role="joint1"><mechanical_reduction>2.0</mechanical_reduction></joint>
      <joint name="joint2" role="joint2"><mechanical_reduction>0.5</mechanical_reduction></joint>
      <actuator name="actuator1" role="actuator1"/>
      <actuator name="actuator2" role="actuator2"/>
    </transmission>

The maps are transmission_interface's (SimpleTransmission, DifferentialTransmission), as one
matrix each (`batchsim.model.Transmission`); the joints and actuators pair up in the order
listed. A transmission that cannot be built is a problem (on_configure fails), named in one line.
"""

from __future__ import annotations

import dataclasses

from batchsim.model.description import ComponentInfo, TransmissionInfo
from batchsim.model.spec import Joint, Transmission, TransmissionKind

_SIZES = {TransmissionKind.SIMPLE: 1, TransmissionKind.DIFFERENTIAL: 2}


@dataclasses.dataclass
class Transmitted:
    """What the transmissions of a description make of its joints.

    Attributes:
      transmissions: the ones built.
      by_joint: ros2_control joint -> (its transmission, its index in it).
      actuator_joints: actuator name -> the MuJoCo joint whose state is the actuator's.
    """

    transmissions: list[Transmission]
    by_joint: dict[str, tuple[Transmission, int]]
    actuator_joints: dict[str, Joint]

    def paired(self, joint: str) -> Joint:
        """Where a transmission joint's state is gathered: its paired actuator's joint,
        under the joint's own name (the transmission then maps the values)."""
        t, k = self.by_joint[joint]
        a = self.actuator_joints[t.actuators[k]]
        return Joint(joint, a.id, a.qposadr, a.dofadr)


def transmissions(
    infos: list[TransmissionInfo],
    components: dict[str, ComponentInfo],
    joints: dict[str, Joint],
    actuated: set[str],
    problems: list[str],
) -> Transmitted:
    """Build `infos`.

    Args:
      components: the blocks' `<joint>`s by name.
      joints: the model's hinge and slide joints by name.
      actuated: names an actuator answers to (the joints actuators drive, actuators' names).
      problems: where a transmission that cannot be built is named.
    """
    out = Transmitted([], {}, {})
    for info in infos:
        t = _build(info, components, joints, actuated, out, problems)
        if t is None:
            continue
        out.transmissions.append(t)
        for k, name in enumerate(t.joints):
            out.by_joint[name] = (t, k)
        for name in t.actuators:
            out.actuator_joints[name] = joints[name]
    return out


def _build(
    info: TransmissionInfo,
    components: dict[str, ComponentInfo],
    joints: dict[str, Joint],
    actuated: set[str],
    out: Transmitted,
    problems: list[str],
) -> Transmission | None:
    at = f"ros2_control transmission {info.name!r}"
    kind = next((k for k in TransmissionKind if k.value == info.plugin), None)
    if kind is None:
        known = ", ".join(k.value for k in TransmissionKind)
        problems.append(f"{at}: plugin {info.plugin!r} is not one batchsim runs (known: {known})")
        return None
    n = _SIZES[kind]
    if len(info.joints) != n or len(info.actuators) != n:
        problems.append(
            f"{at}: a {kind.value.rsplit('/', 1)[1]} takes {n} joint(s) and {n} actuator(s), "
            f"got {len(info.joints)} and {len(info.actuators)}"
        )
        return None
    for end in (*info.joints, *info.actuators):
        if end.bad:
            problems.append(f"{at}: {end.name!r}: {end.bad}")
            return None
        if end.mechanical_reduction == 0.0:
            problems.append(f"{at}: {end.name!r}: mechanical_reduction cannot be zero")
            return None
    for j in info.joints:
        if j.name not in components:
            problems.append(f"{at}: joint {j.name!r} is not a <joint> of the ros2_control block")
            return None
        if j.name in out.by_joint:
            problems.append(f"{at}: joint {j.name!r} is already in transmission {out.by_joint[j.name][0].name!r}")
            return None
        if j.name in actuated:
            problems.append(
                f"{at}: joint {j.name!r} is also driven directly by a MuJoCo actuator: "
                "rename the MJCF joint after the transmission's actuator"
            )
            return None
    for a in info.actuators:
        if a.name not in actuated:
            problems.append(f"{at}: actuator {a.name!r}: the model has no actuator, and no actuated joint, of that name")
            return None
        if a.name not in joints:
            problems.append(f"{at}: actuator {a.name!r}: no hinge or slide joint of that name to read its state from")
            return None
    first = components[info.joints[0].name]
    for j in info.joints[1:]:
        for what in ("command_interfaces", "state_interfaces"):
            if {i.name for i in getattr(components[j.name], what)} != {i.name for i in getattr(first, what)}:
                problems.append(
                    f"{at}: joints {first.name!r} and {j.name!r} must have the same "
                    f"{what.replace('_', ' ')[:-1]}s"
                )
                return None
    if kind is TransmissionKind.SIMPLE:
        matrix = ((info.joints[0].mechanical_reduction,),)
    else:
        (jr0, jr1), (ar0, ar1) = (e.mechanical_reduction for e in info.joints), (
            e.mechanical_reduction for e in info.actuators
        )
        matrix = ((jr0 * ar0, jr1 * ar0), (jr0 * ar1, -jr1 * ar1))
    return Transmission(
        info.name,
        kind,
        tuple(j.name for j in info.joints),
        tuple(a.name for a in info.actuators),
        matrix,
        tuple(j.offset for j in info.joints),
    )
