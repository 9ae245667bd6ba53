"""Per-world randomization (issue 26): batchsim/variation and the contract's batchsim/variation/worlds.py.

Draws depend only on (seed, world, draw number); a world's draw is reproduced alone; cpu, mjx
and warp take the same values and agree on the physics they give; the values really change
the physics; a reset redraws only the worlds it lists; bad input is one line naming file and key.
"""

from __future__ import annotations

import numpy as np
import pytest

import batchsim
from batchsim.cli import main
from batchsim.lifecycle import LifecycleError
from batchsim.types import ConfigurationError
from batchsim.variation import Bound, VariationError, load
from batchsim.variation.worlds import START_QPOS

VARIATION = {
    "seed": 11,
    "fields": [
        {"field": "body_mass", "also": ["body_inertia"], "scale": {"uniform": [0.6, 1.6]}},
        {"field": "geom_friction", "columns": [0], "set": {"uniform": [0.5, 1.5]}, "per": "world"},
        {"field": "dof_damping", "scale": {"loguniform": [0.5, 2.0]}},
        {"field": "dof_armature", "add": {"uniform": [0.0, 0.01]}},
        {"field": "actuator_kp", "scale": {"normal": [1.0, 0.1], "bounds": [0.7, 1.3]}},
        {"field": "opt.gravity", "columns": [2], "add": {"uniform": [-0.5, 0.5]}},
    ],
    "start_pose": {"add": {"normal": [0.0, 0.03]}},
}


def _run(sim: batchsim.BatchedSystem, periods: int = 30) -> np.ndarray:
    """Hold a bent arm for `periods` control periods of 10 steps; the state after."""
    sim.command[:, 1] = 0.8  # joint2 out of the vertical: gravity pulls on it
    for _ in range(periods):
        sim.write()
        sim.step(10)
    sim.read()
    return sim.state.copy()


def _made(backend: str, nworld: int, variation=VARIATION, **kw) -> batchsim.BatchedSystem:
    sim = batchsim.make("arm", nworld, backend, randomize=variation, **kw)
    sim.configure()
    sim.activate()
    return sim


def test_a_draw_depends_only_on_the_seed_and_the_world():
    m = batchsim.load("arm").mjmodel
    bound = Bound(load(VARIATION), m)
    every = bound.draw(np.arange(64), np.zeros(64, np.int64))
    alone = bound.draw(np.array([37]), np.zeros(1, np.int64))
    for field, values in every.items():
        np.testing.assert_array_equal(values[37], alone[field][0])
    assert not np.allclose(every["body_mass"][3], every["body_mass"][4])  # worlds differ
    other = Bound(load({**VARIATION, "seed": 12}), m).draw(np.array([37]), np.zeros(1, np.int64))
    assert not np.allclose(other["body_mass"], alone["body_mass"])  # the seed matters
    again = bound.draw(np.array([37]), np.ones(1, np.int64))
    assert not np.allclose(again["body_mass"], alone["body_mass"])  # a redraw is a new draw
    # every draw inside its distribution
    base = m.body_mass
    scale = every["body_mass"][:, base > 0] / base[base > 0]
    assert scale.min() >= 0.6 and scale.max() <= 1.6
    gain = every["actuator_gainprm"][:, :, 0] / m.actuator_gainprm[:, 0]
    assert gain.min() >= 0.7 - 1e-12 and gain.max() <= 1.3 + 1e-12
    np.testing.assert_allclose(every["actuator_biasprm"][:, :, 1], -every["actuator_gainprm"][:, :, 0])
    np.testing.assert_allclose(every["body_subtreemass"][:, 0], every["body_mass"].sum(axis=1))


def test_a_world_is_reproduced_alone_with_its_offset():
    fleet = _made("cpu", 8)
    alone = _made("cpu", 1, world_offset=5)
    params, own = fleet.world_params(), alone.world_params()
    assert set(params) == {*Bound(load(VARIATION), fleet.model).fields, START_QPOS}
    for field in params:
        np.testing.assert_array_equal(params[field][5], own[field][0])
    np.testing.assert_allclose(_run(fleet)[5], _run(alone)[0], rtol=0, atol=1e-12)


def test_the_varied_masses_change_the_physics():
    """A heavier arm sags more under gravity against the same position servo."""
    variation = {"seed": 3, "fields": [{"field": "body_mass", "also": ["body_inertia"], "scale": {"uniform": [0.3, 3.0]}, "per": "world"}]}
    sim = _made("cpu", 6, variation)
    plain = _made("cpu", 1, None)
    sag = np.abs(_run(sim, 400)[:, 3] - 0.8)  # joint2's position against its command
    scale = sim.world_params()["body_mass"][:, 2] / sim.model.body_mass[2]
    order = np.argsort(scale)
    assert np.all(np.diff(sag[order]) > 0), (scale[order], sag[order])
    assert sag.min() > 0
    nominal_sag = abs(_run(plain, 400)[0, 3] - 0.8)
    assert sag[scale < 1].max() < nominal_sag < sag[scale > 1].min()


def test_a_reset_redraws_only_the_worlds_it_lists():
    sim = _made("cpu", 4, {**VARIATION, "redraw_on_reset": True})
    before = sim.world_params()
    sim.reset([2])
    after = sim.world_params()
    assert list(sim.draw_numbers()) == [0, 0, 1, 0]
    for field in before:
        np.testing.assert_array_equal(np.delete(after[field], 2, axis=0), np.delete(before[field], 2, axis=0))
    assert not np.allclose(after["body_mass"][2], before["body_mass"][2])
    np.testing.assert_allclose(sim.state[2, 0], after[START_QPOS][2, 0])  # the new start pose, shown
    # the second draw of world 2 is the same as a lone world 2's second draw
    alone = _made("cpu", 1, {**VARIATION, "redraw_on_reset": True}, world_offset=2)
    alone.reset()
    np.testing.assert_array_equal(alone.world_params()["body_mass"][0], after["body_mass"][2])
    # without redraw_on_reset, a reset world keeps its draw
    kept = _made("cpu", 4)
    first = kept.world_params()
    kept.reset([1, 3])
    for field, values in kept.world_params().items():
        np.testing.assert_array_equal(values, first[field])


def test_kp_and_kv_are_a_position_servos_gains():
    """actuator_kp scales gainprm[0] and -biasprm[1] together, actuator_kv -biasprm[2]: the
    servo's stiffness and damping, and nothing else of the actuator."""
    m = batchsim.load("arm").mjmodel
    kv = {"fields": [{"field": "actuator_kv", "names": ["joint1"], "scale": {"uniform": [2.0, 3.0]}}]}
    drawn = Bound(load(kv), m).draw(np.arange(3), np.zeros(3, np.int64))
    bias = drawn["actuator_biasprm"]
    assert "actuator_gainprm" not in drawn  # a position servo's kv lives in biasprm alone
    scale = bias[:, 0, 2] / m.actuator_biasprm[0, 2]
    assert np.all((scale >= 2.0) & (scale <= 3.0)) and len(set(scale)) == 3
    np.testing.assert_array_equal(bias[:, 1:], np.broadcast_to(m.actuator_biasprm[1:], bias[:, 1:].shape))
    np.testing.assert_array_equal(bias[:, 0, :2], np.broadcast_to(m.actuator_biasprm[0, :2], (3, 2)))
    kp = {"fields": [{"field": "actuator_kp", "set": {"uniform": [50.0, 60.0]}, "per": "world"}]}
    drawn = Bound(load(kp), m).draw(np.arange(2), np.zeros(2, np.int64))
    assert np.all(drawn["actuator_gainprm"][:, :, 0] == drawn["actuator_gainprm"][:, :1, 0])  # one draw per world
    np.testing.assert_array_equal(drawn["actuator_biasprm"][:, :, 1], -drawn["actuator_gainprm"][:, :, 0])
    with pytest.raises(VariationError, match=r"fields\[0\].set: uniform\(-5, 1\) can make actuator_gainprm negative"):
        Bound(load({"fields": [{"field": "actuator_kp", "set": {"uniform": [-5, 1]}}]}), m)


def test_a_start_pose_is_held_by_its_commands():
    sim = _made("cpu", 3, {"start_pose": {"joints": ["joint2", "joint3"], "add": {"uniform": [-0.2, 0.2]}}})
    start = sim.world_params()[START_QPOS]
    assert np.all(start[:, [0, 3, 4, 5]] == 0) and np.all(start[:, 1:3] != 0)
    np.testing.assert_allclose(sim.command[:, 1:3], start[:, 1:3])
    for _ in range(20):
        sim.write()
        sim.step(10)
    sim.read()
    np.testing.assert_allclose(sim.state[:, [3, 6]], start[:, 1:3], atol=0.02)  # stays near where it started


# |backend - cpu| of the joints after 0.3 s of a 0.8 rad step: float32 against float64. Without
# a variation the same run parts by 1.3e-4 rad on mjx and 1e-7 on warp; with it by 4.6e-4 and 5e-7
# (each field alone: 1.3e-4 to 2.5e-4 on mjx, the stiffer servos the most).
TOLERANCE = {"mjx": 1e-3, "warp": 1e-5}


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_every_backend_takes_the_same_draw_and_gives_the_same_physics(backend):
    reference = _made("cpu", 4)
    sim = _made(backend, 4)
    for field, values in reference.world_params().items():
        np.testing.assert_array_equal(sim.world_params()[field], values)
    positions = slice(0, 18, 3)  # the six joints' position columns
    np.testing.assert_allclose(sim.state[:, positions], reference.state[:, positions], atol=1e-6)  # the start pose
    ran = _run(reference)[:, positions]
    np.testing.assert_allclose(_run(sim)[:, positions], ran, atol=TOLERANCE[backend])
    assert np.abs(_run(_made("cpu", 4, None))[:, positions] - ran).max() > 50 * TOLERANCE[backend]  # it varied


@pytest.mark.parametrize("backend", ["mjx", "warp"])
def test_a_redraw_reaches_the_device(backend):
    variation = {"seed": 5, "redraw_on_reset": True, "fields": [{"field": "body_mass", "scale": {"uniform": [0.3, 3.0]}, "per": "world"}]}
    sim, reference = _made(backend, 3, variation), _made("cpu", 3, variation)
    for s in (sim, reference):
        _run(s, 5)
        s.reset([0, 2])
    np.testing.assert_allclose(_run(sim, 60)[:, 3], _run(reference, 60)[:, 3], atol=TOLERANCE[backend])


def test_a_sharded_warp_fleet_draws_as_one_device():
    one = _made("warp", 5)
    two = _made("warp", 5, devices=["cpu", "cpu"])
    try:
        for field, values in one.world_params().items():
            np.testing.assert_array_equal(two.world_params()[field], values)
        np.testing.assert_allclose(two.state, one.state, atol=1e-6)
        for fleet in (one, two):  # a reseed reaches the shards: their next draw is the new seed's
            fleet.reseed(4)
            fleet.reset()
        for field, values in one.world_params().items():
            np.testing.assert_array_equal(two.world_params()[field], values)
        with pytest.raises(batchsim.ConfigurationError, match="several devices has no one device array"):
            two.device_state()
    finally:
        two.shutdown()


@pytest.mark.parametrize(
    ("variation", "message"),
    [
        ({"fields": [{"field": "body_mas", "scale": {"uniform": [1, 2]}}]}, r"fields\[0\].field: body_mas is not .*did you mean body_mass"),
        ({"fields": [{"field": "body_mass", "scale": {"uniform": [2, 1]}}]}, r"fields\[0\].scale.uniform: low 2 > high 1"),
        ({"fields": [{"field": "body_mass", "add": {"uniform": [-5, 0]}}]}, r"fields\[0\].add: .*body_mass non-positive"),
        ({"fields": [{"field": "body_mass", "scale": {"normal": [1, 0.2]}}]}, r"fields\[0\].scale: a scale must stay >= 0"),
        ({"fields": [{"field": "body_mass", "names": ["nope"], "scale": {"uniform": [1, 2]}}]}, r"names: no body named 'nope'"),
        ({"fields": [{"field": "geom_friction", "columns": [5], "scale": {"uniform": [1, 2]}}]}, r"columns: geom_friction has 3 columns"),
        ({"fields": [{"field": "opt.timestep", "scale": {"uniform": [1, 2]}}]}, r"opt.timestep cannot vary per world"),
        ({"fields": [{"field": "body_mass", "mul": {"uniform": [1, 2]}}]}, r"fields\[0\]: unknown key 'mul'"),
        ({"fields": [{"field": "dof_damping", "scale": {"loguniform": [0, 2]}}]}, r"loguniform: low must be > 0"),
        ({"start_pose": {"joints": ["nope"], "add": {"normal": [0, 0.1]}}}, r"start_pose.joints: no joint named 'nope'"),
        ({"sed": 3}, r"unknown key 'sed'"),
    ],
)
def test_bad_input_is_one_line_naming_the_key(variation, message):
    with pytest.raises(VariationError, match=message) as caught:
        batchsim.make("arm", 2, "cpu", randomize=variation)
    assert "\n" not in str(caught.value) and str(caught.value).startswith("<mapping>: randomize")


def test_a_field_warp_cannot_vary_is_refused_naming_the_backends_that_can():
    with pytest.raises(ConfigurationError, match=r"^<mapping>: randomize.fields\[0\]: the warp backend cannot vary opt.impratio per world; backends that can: cpu, mjx$"):
        batchsim.make("arm", 2, "warp", randomize={"fields": [{"field": "opt.impratio", "scale": {"uniform": [1, 2]}}]})


def test_the_variation_is_set_before_configure():
    sim = _made("cpu", 2)
    with pytest.raises(LifecycleError, match="before configure"):
        sim.set_variation(VARIATION)


def test_the_command_line_names_the_file_and_shows_the_draws(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("randomize:\n  fields:\n    - {field: body_mass, scale: {uniform: [2, 1]}}\n")
    assert main(["--worlds", "2", "--no-ros", "--randomize", str(bad), "--duration", "0.01"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"batchsim: error: {bad}: randomize.fields[0].scale.uniform: low 2 > high 1"]
    good = tmp_path / "good.yaml"
    good.write_text("randomize:\n  seed: 4\n  fields:\n    - {field: body_mass, names: [link1], scale: {uniform: [0.5, 1.5]}}\n")
    assert main(["info", "arm", "--randomize", str(good), "--worlds", "2", "--world-offset", "7"]) == 0
    out = capsys.readouterr().out
    mass = Bound(load(good), batchsim.load("arm").mjmodel).draw(np.array([7]), np.zeros(1, np.int64))["body_mass"][0, 2]
    assert "body_mass [link1]: scale uniform(0.5, 1.5), a draw per object" in out
    assert f"world 7:\n    body_mass link1={mass:.6g}" in out and "world 8:" in out
