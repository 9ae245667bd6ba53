"""The policy controller (batchsim/PolicyController), in-process, with tiny ONNX graphs built
here from known weights: its actions are checked against the ones computed by hand from the
declared terms, per world, with the policy's joint order unlike the model's."""

from __future__ import annotations

import logging
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import need

import batchsim
from batchsim.controllers import load_controllers
from batchsim.loop import SimLoop
from batchsim.types import ConfigurationError, Status

onnx = need("onnx")
need("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

ARM = [f"joint{i}" for i in range(1, 7)]
ORDER = ["joint3", "joint1", "joint2", "joint6", "joint4", "joint5"]  # the policy's, not the MJCF's


def linear_policy(
    path: Path, weights: np.ndarray, bias: np.ndarray, *, log: bool = False, metadata=None
) -> Path:
    """An ONNX graph: actions = obs @ weights + bias (then log() of it with `log`), batch symbolic."""
    nobs, nact = weights.shape
    nodes = [
        helper.make_node("MatMul", ["obs", "W"], ["xw"]),
        helper.make_node("Add", ["xw", "b"], ["lin" if log else "actions"]),
    ]
    if log:
        nodes.append(helper.make_node("Log", ["lin"], ["actions"]))
    graph = helper.make_graph(
        nodes,
        "policy",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", nobs])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", nact])],
        initializer=[
            numpy_helper.from_array(weights.astype(np.float32), "W"),
            numpy_helper.from_array(bias.astype(np.float32), "b"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for key, value in (metadata or {}).items():
        model.metadata_props.append(onnx.StringStringEntryProto(key=key, value=value))
    onnx.save(model, path)
    return path


def controllers_yaml(tmp_path: Path, policy: str, rate: int = 100, extra: str = "") -> Path:
    path = tmp_path / "policy.yaml"
    path.write_text(
        textwrap.dedent(
            f"""\
            controller_manager:
              ros__parameters:
                update_rate: {rate}
                joint_state_broadcaster:
                  type: joint_state_broadcaster/JointStateBroadcaster
                policy_controller:
                  type: batchsim/PolicyController
            policy_controller:
              ros__parameters:
            """
        )
        + textwrap.indent(textwrap.dedent(policy), " " * 4)
        + textwrap.dedent(extra)
    )
    return path


def running(yaml: Path, nworld: int):
    sim = batchsim.make("arm", nworld, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    manager = load_controllers(yaml, sim.spec, nworld)
    loop = SimLoop(sim, control_rate=manager.update_rate, rtf=0, participants=[manager])
    return sim, manager, loop


def columns(sim, names):
    return [sim.export_state_interfaces().index(n) for n in names]


NOBS = 6 + 6 + 6 + 6  # joint_pos, joint_vel, command, actions
SPEC = f"""\
model: policy.onnx
joints: {ORDER}
default_positions: [0.1, -0.2, 0.3, 0.0, 0.05, -0.1]
observations: [joint_pos, joint_vel, command, actions]
terms:
  joint_vel: {{scale: 0.1}}
action:
  scale: 0.5
policy_rate: 50.0
"""


def test_actions_are_the_ones_computed_by_hand_from_the_terms_per_world_in_the_policys_joint_order(tmp_path):
    rng = np.random.default_rng(3)
    weights, bias = rng.normal(scale=0.2, size=(NOBS, 6)), rng.normal(scale=0.1, size=6)
    linear_policy(tmp_path / "policy.onnx", weights, bias)
    sim, manager, loop = running(controllers_yaml(tmp_path, SPEC), 3)
    policy = manager["policy_controller"]
    default = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.1])
    commands = np.array([[0.2, 0.1, -0.3, 0.0, 0.4, 0.2], [0.0] * 6, [-0.5, 0.3, 0.2, 0.1, -0.1, 0.0]])
    assert policy.set_commands([0, 1, 2], commands) == []
    # a few periods so that the joints move and the last action is not zero
    for _ in range(6):
        loop.run_period()
    sim.read()
    pos = sim.state[:, columns(sim, [f"{j}/position" for j in ORDER])]
    vel = sim.state[:, columns(sim, [f"{j}/velocity" for j in ORDER])]
    last = policy.actions.copy()
    assert np.abs(last).max() > 0
    obs = np.concatenate([pos - default, 0.1 * vel, commands, last], axis=1).astype(np.float32)
    expected = obs @ weights.astype(np.float32) + bias.astype(np.float32)
    before = policy.inferences
    loop.run_period()  # period 7 of a 100 Hz loop: the 50 Hz policy runs (every second period)
    assert policy.inferences == before + 1
    np.testing.assert_allclose(policy.actions, expected, rtol=1e-5, atol=1e-6)
    # the targets went to the joints by name: joint3's position interface got the first entry
    ci = sim.export_command_interfaces()
    for k, joint in enumerate(ORDER):
        np.testing.assert_allclose(
            sim.command[:, ci.index(f"{joint}/position")],
            default[k] + 0.5 * expected[:, k],
            rtol=1e-5,
            atol=1e-6,
        )


def test_decimation_holds_the_action_between_policy_periods(tmp_path):
    linear_policy(tmp_path / "policy.onnx", np.full((NOBS, 6), 0.01), np.zeros(6))
    sim, manager, loop = running(
        controllers_yaml(tmp_path, SPEC.replace("policy_rate: 50.0", "policy_rate: 25.0")), 2
    )
    policy = manager["policy_controller"]
    policy.set_commands([0, 1], [[0.3] * 6, [-0.3] * 6])
    targets = []
    for _ in range(8):
        loop.run_period()
        targets.append(policy.targets.copy())
    assert policy.decimation == 4 and policy.inferences == 2
    for k in (1, 2, 3):
        np.testing.assert_array_equal(targets[k], targets[0])
    assert not np.array_equal(targets[4], targets[0])  # a new inference, from a moved arm


def test_a_nan_action_gives_that_world_bad_command_and_holds_its_last_action(tmp_path, caplog):
    # actions = log(command[0]): a negative command entry makes that world's actions NaN
    weights = np.zeros((NOBS, 6))
    weights[12, :] = 1.0  # command's first entry
    linear_policy(tmp_path / "policy.onnx", weights, np.zeros(6), log=True)
    spec = SPEC.replace("policy_rate: 50.0", "").replace(
        "command, actions", "command, actions]\ncommand: {default: [1, 1, 1, 1, 1, 1]}\n#"
    )
    sim, manager, loop = running(controllers_yaml(tmp_path, spec), 3)
    policy = manager["policy_controller"]
    policy.set_commands([0, 1, 2], [[2.0] + [0.0] * 5] * 3)
    for _ in range(3):
        loop.run_period()
    held_action = policy.actions[1].copy()
    ctrl_before = sim.ctrl()[1].copy()
    other_before = sim.command[[0, 2]].copy()
    policy.set_commands([1], [[-1.0] + [0.0] * 5])
    with caplog.at_level(logging.WARNING, logger="batchsim.controllers.policy"):
        loop.run_period()
        loop.run_period()
    assert sim.status[1] & Status.BAD_COMMAND
    assert not (sim.status[[0, 2]] & Status.BAD_COMMAND).any()
    np.testing.assert_array_equal(policy.actions[1], held_action)  # the last finite action, kept
    np.testing.assert_array_equal(sim.ctrl()[1], ctrl_before)  # its ctrl held
    np.testing.assert_array_equal(sim.command[[0, 2]], other_before)  # the others untouched (same command)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "policy_controller" in lines[0] and "worlds [1]" in lines[0]
    policy.set_commands([1], [[2.0] + [0.0] * 5])  # finite again: applied, the status clears
    loop.run_period()
    loop.run_period()
    assert not sim.status[1] & Status.BAD_COMMAND


def test_an_mjlab_export_needs_no_hand_written_spec(tmp_path):
    metadata = {
        "joint_names": ",".join(ORDER),
        "default_joint_pos": "0.1,-0.2,0.3,0.0,0.05,-0.1",
        "action_scale": "0.25",
        "observation_names": "joint_pos,joint_vel,actions,command",
    }
    weights = np.zeros((NOBS, 6))
    weights[18:, :] = np.eye(6)  # actions = command (the last term), whatever the terms' order above
    linear_policy(tmp_path / "policy.onnx", weights, np.zeros(6), metadata=metadata)
    sim, manager, loop = running(controllers_yaml(tmp_path, "model: policy.onnx\n"), 2)
    policy = manager["policy_controller"]
    assert policy.policy.joints == tuple(ORDER)
    assert [t.name for t in policy.policy.terms] == ["joint_pos", "joint_vel", "actions", "command"]
    policy.set_commands([0, 1], [[0.4] * 6, [-0.4] * 6])
    loop.run_period()
    ci = sim.export_command_interfaces()
    default = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.1])
    for k, joint in enumerate(ORDER):
        np.testing.assert_allclose(
            sim.command[:, ci.index(f"{joint}/position")],
            default[k] + 0.25 * np.array([0.4, -0.4]),
            atol=1e-6,
        )


def test_switching_per_world_between_the_policy_and_the_trajectory_controller(tmp_path):
    weights = np.zeros((NOBS, 6))
    weights[12:18, :] = np.eye(6)  # actions = command: the targets are default + command
    linear_policy(tmp_path / "policy.onnx", weights, np.zeros(6))
    extra = f"""\
    joint_trajectory_controller:
      ros__parameters:
        joints: {ARM}
        command_interfaces: [position]
        state_interfaces: [position, velocity]
    """
    yaml = controllers_yaml(
        tmp_path, SPEC.replace("policy_rate: 50.0", "").replace("scale: 0.5", "scale: 1.0"), extra=extra
    )
    text = yaml.read_text().replace(
        "      type: batchsim/PolicyController\n",
        "      type: batchsim/PolicyController\n    joint_trajectory_controller:\n      type: joint_trajectory_controller/JointTrajectoryController\n",
    )
    yaml.write_text(text)
    sim, manager, loop = running(yaml, 4)
    # both claim the arm's positions: the policy runs where it was activated, the JTC elsewhere
    result = manager.switch([0, 1], deactivate=["joint_trajectory_controller"])
    assert result.ok, result
    result = manager.switch([2, 3], deactivate=["policy_controller"])
    assert result.ok, result
    policy = manager["policy_controller"]
    target = np.array([0.3, -0.2, 0.4, 0.2, -0.3, 0.1])
    policy.set_commands(np.arange(4), np.tile(target, (4, 1)))
    pos = columns(sim, [f"{j}/position" for j in ORDER])
    start = sim.state[:, pos].copy()
    for _ in range(150):
        loop.run_period()
    default = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.1])
    ci = [sim.export_command_interfaces().index(f"{j}/position") for j in ORDER]
    np.testing.assert_allclose(
        sim.command[:2][:, ci], np.tile(default + target, (2, 1)), atol=1e-6
    )  # float32 actions
    # the position servos sag under gravity (up to ~0.09 rad at the shoulder and elbow)
    np.testing.assert_allclose(sim.state[:2][:, pos], np.tile(default + target, (2, 1)), atol=0.1)
    np.testing.assert_allclose(sim.state[2:][:, pos], start[2:], atol=0.05)  # the JTC holds them
    # and back: world 2 to the policy, world 0 to the JTC (which holds where it is)
    assert manager.switch([2], activate=["policy_controller"], deactivate=["joint_trajectory_controller"]).ok
    assert manager.switch([0], activate=["joint_trajectory_controller"], deactivate=["policy_controller"]).ok
    loop.run_period()  # the switch takes effect: the policy starts world 2 from its default command
    np.testing.assert_array_equal(policy.commands[2], default)
    policy.set_commands([2], [target])
    held = sim.state[0, pos].copy()
    for _ in range(150):
        loop.run_period()
    np.testing.assert_allclose(sim.command[2, ci], default + target, atol=1e-6)
    np.testing.assert_allclose(sim.state[2, pos], default + target, atol=0.1)
    # the JTC holds world 0 where it was at the switch (its command; the servo sags below it)
    np.testing.assert_allclose(sim.command[0, ci], held, atol=0.01)


# ---------------------------------------------------------------- bad input, one line each


def _error(tmp_path, spec: str, weights_shape=(NOBS, 6)) -> str:
    if not (tmp_path / "policy.onnx").exists():
        linear_policy(tmp_path / "policy.onnx", np.zeros(weights_shape), np.zeros(weights_shape[1]))
    with pytest.raises(ConfigurationError) as e:
        running(controllers_yaml(tmp_path, spec), 1)
    message = str(e.value)
    assert "\n" not in message and "policy_controller" in message
    return message


def test_a_file_that_is_not_onnx(tmp_path):
    (tmp_path / "policy.onnx").write_text("not a model")
    message = _error(tmp_path, SPEC)
    assert "policy.onnx is not an ONNX model" in message and "model" in message


def test_a_missing_model_file(tmp_path):
    message = _error(tmp_path, SPEC.replace("policy.onnx", "gone.onnx"))
    assert "no such file" in message and "gone.onnx" in message


def test_an_observation_size_that_does_not_match_names_each_terms_share(tmp_path):
    message = _error(tmp_path, SPEC, weights_shape=(NOBS + 3, 6))
    assert f"takes {NOBS + 3} observation values, the terms give {NOBS}" in message
    assert "joint_pos 6, joint_vel 6, command 6, actions 6" in message


def test_an_action_size_that_does_not_match_the_joints(tmp_path):
    message = _error(tmp_path, SPEC, weights_shape=(NOBS, 4))
    assert "gives 4 actions, the controller has 6 joints" in message


def test_a_joint_the_robot_lacks(tmp_path):
    message = _error(tmp_path, SPEC.replace("joint6", "elbow"))
    assert "joints: the model has no joint 'elbow'" in message


def test_an_unknown_term_and_an_unknown_sensor(tmp_path):
    assert "unknown term 'joint_torque'" in _error(
        tmp_path, SPEC.replace("command, actions", "command, joint_torque")
    )
    message = _error(tmp_path, SPEC.replace("command, actions", "command, 'sensor:elbow_imu'"))
    assert "the model has no sensor 'elbow_imu'" in message


def test_a_sensor_term_reads_the_named_sensor(tmp_path):
    # wrist_force is 3 wide: the observation grows by 3 in place of `actions`
    weights = np.zeros((NOBS - 3, 6))
    weights[18:21, 0] = 1.0  # action 0 = the force's sum
    linear_policy(tmp_path / "policy.onnx", weights, np.zeros(6))
    sim, manager, loop = running(
        controllers_yaml(tmp_path, SPEC.replace("command, actions", "command, 'sensor:wrist_force'")), 2
    )
    policy = manager["policy_controller"]
    for _ in range(2):
        loop.run_period()
    sim.read()
    force = sim.sensordata["wrist_force"].sum(axis=1)
    loop.run_period()
    np.testing.assert_allclose(policy.actions[:, 0], force, rtol=1e-4, atol=1e-4)


def test_a_bad_command_is_refused_with_its_reason_and_the_world_keeps_its_own(tmp_path):
    linear_policy(tmp_path / "policy.onnx", np.zeros((NOBS, 6)), np.zeros(6))
    sim, manager, _ = running(controllers_yaml(tmp_path, SPEC), 2)
    policy = manager["policy_controller"]
    rejected = policy.set_commands([0, 1, 5], [[0.1] * 6, [np.nan] * 6, [0.2] * 6])
    assert [k for k, _ in rejected] == [1, 2]
    assert "finite" in rejected[0][1] and "world" in rejected[1][1]
    np.testing.assert_allclose(policy.commands[0], 0.1)
    np.testing.assert_allclose(policy.commands[1], [0.1, -0.2, 0.3, 0.0, 0.05, -0.1])  # its default


# ---------------------------------------------------------------- export, the shipped policy, evaluate


def test_an_exported_perceptron_computes_what_numpy_computes(tmp_path):
    from batchsim.controllers.policy.export import export_mlp, mlp_forward
    from batchsim.controllers.policy.runtime import PolicyRuntime

    rng = np.random.default_rng(0)
    layers = [
        (rng.normal(size=(10, 16)), rng.normal(size=16)),
        (rng.normal(size=(16, 16)), rng.normal(size=16)),
        (rng.normal(size=(16, 3)), rng.normal(size=3)),
    ]
    for activation in ("tanh", "elu", "relu"):
        path = export_mlp(tmp_path / f"{activation}.onnx", layers, activation, {"joint_names": "a,b,c"})
        runtime = PolicyRuntime(path, "test")
        obs = rng.normal(size=(7, 10)).astype(np.float32)
        np.testing.assert_allclose(runtime(obs), mlp_forward(layers, activation, obs), rtol=1e-5, atol=1e-5)
        assert runtime.metadata["joint_names"] == "a,b,c" and (runtime.obs_size, runtime.action_size) == (
            10,
            3,
        )


EXAMPLES = Path(__file__).resolve().parent.parent / "examples" / "policies"


def _evaluate(tmp_path, *extra: str) -> dict:
    import json

    from batchsim.cli import main

    out = tmp_path / f"report{len(list(tmp_path.glob('report*')))}.json"
    argv = ["evaluate", "--model", "arm", "--controllers", str(EXAMPLES / "arm_reach.yaml"),
            "--randomize", str(EXAMPLES / "randomize.yaml"), "--json", str(out), *extra]  # fmt: skip
    assert main(argv) == 0
    return json.loads(out.read_text())


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_the_shipped_policy_reaches_its_targets_across_randomized_worlds_and_a_world_repeats_alone(
    tmp_path, capsys
):
    report = _evaluate(
        tmp_path,
        "--worlds",
        "12",
        "--episodes",
        "2",
        "--episode-seconds",
        "2",
        "--plot",
        str(tmp_path / "r.png"),
    )
    assert report["success_rate"] >= 0.8, report["success_rate"]
    assert len(report["worlds"]) == 12 and (tmp_path / "r.png").stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "success" in printed and "worst" in printed and "--worlds 1 --world-offset" in printed
    # each episode its own draw of the conditions, and its own command
    world = report["worlds"][7]
    assert [e["draw"] for e in world["episodes"]] == [0, 1]
    assert world["episodes"][0]["params"] != world["episodes"][1]["params"]
    assert world["episodes"][0]["command"] != world["episodes"][1]["command"]
    # world 7 alone draws and is commanded as it was in the fleet, and does the same
    alone = _evaluate(
        tmp_path, "--worlds", "1", "--world-offset", "7", "--episodes", "2", "--episode-seconds", "2"
    )
    assert alone["worlds"][0]["world"] == 7
    for mine, fleet in zip(alone["worlds"][0]["episodes"], world["episodes"], strict=True):
        assert mine["command"] == fleet["command"] and mine["params"] == fleet["params"]
        assert mine["final_error"] == pytest.approx(fleet["final_error"], abs=1e-6)


def test_evaluate_refuses_a_yaml_without_a_policy_in_one_line(tmp_path, capsys):
    from batchsim.cli import main
    from batchsim.controllers import default_controllers

    assert main(["evaluate", "--controllers", str(default_controllers("arm"))]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "policy controller" in err


def test_a_terms_history_stacks_its_last_values_oldest_first_and_a_reset_refills_it(tmp_path):
    # joint_pos with history 3 (the policy at the control rate): action_j = q_old + 10 q_mid + 100 q_new
    weights = np.zeros((18, 6))
    for k, c in enumerate((1.0, 10.0, 100.0)):
        weights[6 * k : 6 * k + 6] = c * np.eye(6)
    linear_policy(tmp_path / "policy.onnx", weights, np.zeros(6))
    spec = f"model: policy.onnx\njoints: {ARM}\nobservations: [joint_pos_abs]\nterms:\n  joint_pos_abs: {{history: 3}}\naction: {{scale: 0.0}}\n"
    # scale 0: the targets are the default pose, away from the start, so the joints move every period
    spec += "default_positions: [0.5, -0.4, 0.6, 0.3, -0.5, 0.8]\n"
    sim, manager, loop = running(controllers_yaml(tmp_path, spec), 2)
    policy = manager["policy_controller"]
    pos = columns(sim, [f"{j}/position" for j in ARM])
    seen = []
    for _ in range(4):
        sim.read()
        seen.append(sim.state[:, pos].copy())
        loop.run_period()
    q = seen
    assert np.abs(q[3] - q[2]).min() > 1e-4 and np.abs(q[2] - q[1]).min() > 1e-5  # they moved
    np.testing.assert_allclose(policy.actions, q[1] + 10 * q[2] + 100 * q[3], rtol=1e-5, atol=1e-5)
    # a reset world's history is its next step, repeated (Isaac Lab's reset); the other keeps its own
    manager.on_reset(sim, np.array([1]))
    sim.read()
    now = sim.state[:, pos].copy()
    loop.run_period()
    np.testing.assert_allclose(policy.actions[1], 111 * now[1], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(policy.actions[0], q[2][0] + 10 * q[3][0] + 100 * now[0], rtol=1e-5, atol=1e-5)


def test_a_velocity_policy_reads_the_base_in_its_own_frame_takes_cmd_vel_and_drives_efforts(tmp_path):
    import mujoco

    from batchsim.controllers.topics import MessageKind

    legs = [
        f"{leg}_{j}" for leg in ("FL", "FR", "HL", "HR") for j in ("hip_abduction", "hip_flexion", "knee")
    ]
    rng = np.random.default_rng(5)
    weights, bias = rng.normal(scale=0.3, size=(12, 12)), rng.normal(scale=0.1, size=12)
    linear_policy(tmp_path / "policy.onnx", weights, bias)
    spec = (
        f"model: policy.onnx\njoints: {legs}\nobservations: [base_lin_vel, base_ang_vel, projected_gravity, velocity_commands]\n"
        "action: {interface: effort, scale: 2.0}\ncommand: {kind: velocity}\n"
    )
    path = tmp_path / "policy.yaml"
    path.write_text(
        "controller_manager:\n  ros__parameters:\n    update_rate: 100\n"
        "    policy_controller:\n      type: batchsim/PolicyController\n"
        "policy_controller:\n  ros__parameters:\n" + textwrap.indent(spec, "    ")
    )
    sim = batchsim.make("quadruped", 3, "cpu", nthread=1)
    sim.configure()
    sim.activate()
    manager = load_controllers(path, sim.spec, 3)
    loop = SimLoop(sim, control_rate=100.0, rtf=0, participants=[manager])
    policy = manager["policy_controller"]
    (command,) = policy.topics().inputs
    assert command.topic == "policy_controller/cmd_vel" and command.kind is MessageKind.TWIST
    twists = np.array([[0.5, 0.1, 0, 0, 0, 0.3], [0.0, -0.2, 0, 0, 0, -0.1], [1.0, 0.0, 0, 0, 0, 0.0]])
    assert command.apply(np.arange(3), twists) == []
    for _ in range(30):  # it falls and tumbles under random efforts: the base moves and tilts
        loop.run_period()
    sim.read()
    base = sim.base_state.copy()
    expected_obs = []
    for w in range(3):
        conj = base[w, 3:7] * [1, -1, -1, -1]
        lin, grav = np.zeros(3), np.zeros(3)
        mujoco.mju_rotVecQuat(lin, base[w, 7:10], conj)
        mujoco.mju_rotVecQuat(grav, np.array([0.0, 0.0, -1.0]), conj)
        expected_obs.append(np.concatenate([lin, base[w, 10:13], grav, twists[w, [0, 1, 5]]]))
    assert np.abs(np.array(expected_obs)[:, :3]).max() > 0.01  # it moves
    expected = np.array(expected_obs, np.float32) @ weights.astype(np.float32) + bias.astype(np.float32)
    loop.run_period()
    np.testing.assert_allclose(policy.actions, expected, rtol=1e-4, atol=1e-4)
    ci = sim.export_command_interfaces()
    np.testing.assert_allclose(
        sim.command[:, [ci.index(f"{j}/effort") for j in legs]], 2.0 * expected, rtol=1e-4, atol=1e-4
    )


@pytest.mark.slow  # over a few seconds: `make quick` leaves it out
def test_the_training_script_trains_and_exports_a_policy_the_controller_runs(tmp_path):
    """A short run of examples/policies/train_arm_reach.py (the `train` extra: stable-baselines3
    and PyTorch, not in `all`; skipped where they are absent)."""
    import importlib.util

    if importlib.util.find_spec("stable_baselines3") is None:  # not `need`: CI installs `all`, which leaves it out
        pytest.skip("stable_baselines3 is not installed (pip install -e '.[train]')")

    spec = importlib.util.spec_from_file_location("train_arm_reach", EXAMPLES / "train_arm_reach.py")
    train = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(train)
    out = tmp_path / "arm_reach.onnx"
    train.main(["--worlds", "8", "--steps", "1024", "--out", str(out)])
    yaml = tmp_path / "arm_reach.yaml"
    yaml.write_text((EXAMPLES / "arm_reach.yaml").read_text())
    sim, manager, loop = running(yaml, 2)
    policy = manager["arm_reach_controller"]
    assert policy.runtime.metadata["observation_names"] == "joint_pos,joint_vel,command,actions"
    assert policy.runtime.metadata["joint_names"] == ",".join(ARM)
    loop.run_period()
    assert np.isfinite(policy.actions).all() and policy.inferences == 1
