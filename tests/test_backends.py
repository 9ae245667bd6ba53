"""The backend registry (batchsim.backends): a backend from outside batchsim is one class and one
`register` line (issue 22; tests/reference_backend.py is one, registered in conftest.py and run
through the contract suite), taken by name wherever a shipped one is; what a backend can do is
stated by its class, not looked up by its name."""

from __future__ import annotations

import pytest
from conftest import need
from reference_backend import ReferenceEngine

import batchsim
from batchsim import backends, cli
from batchsim.backends import Backend, Registered, backend_class, parse, register
from batchsim.cli import runner
from batchsim.cli.args import run_parser
from batchsim.loop import OptionError


@pytest.fixture
def registry(monkeypatch):
    """The registry as it is, given back as it was after the test."""
    monkeypatch.setattr(backends, "_REGISTERED", dict(backends._REGISTERED))


def test_a_registered_backend_is_taken_by_name_wherever_a_backend_is(capsys):
    ref = parse("REF")
    assert isinstance(ref, Registered) and ref.cls is ReferenceEngine and ref.value == "ref"
    assert backends.names() == ["auto", "cpu", "mjx", "warp", "ref"]
    sim = batchsim.make("arm", 2, "Ref")
    assert isinstance(sim.engine, ReferenceEngine) and sim.reason == "requested"
    assert backends.resolve("ref", sim.spec, 2) == (ref, "requested")
    # an unknown name: the same one line, the registered names among the choices
    with pytest.raises(OptionError, match=r"^unknown backend 'nope' \(choose from auto, cpu, mjx, warp, ref\)$"):
        parse("nope")
    # the command line: its help names it, a run takes it, an unknown name is the same one line
    (flag,) = [a for a in run_parser()._actions if "--backend" in a.option_strings]
    assert flag.help.startswith("cpu, mjx, warp, ref or auto")
    run = ["--backend", "ref", "--no-ros", "--worlds", "2", "--duration", "0.02", "--rtf", "0", "--controllers", "none"]
    assert cli.main(run) == 0
    assert "2 x arm on ref (requested)" in capsys.readouterr().err
    assert cli.main(["--backend", "nope", "--no-ros"]) == 2
    unknown = "batchsim: error: unknown backend 'nope' (choose from auto, cpu, mjx, warp, ref)"
    assert capsys.readouterr().err.strip() == unknown


def test_register_refuses_a_name_that_would_be_ambiguous(registry):
    class Other(ReferenceEngine):
        name = "other"

    with pytest.raises(ValueError, match="'CPU' is one of batchsim's own"):
        register("CPU", Other)
    with pytest.raises(ValueError, match=r"Other.name is 'other'; it must be the name registered"):
        register("another", Other)
    with pytest.raises(ValueError, match="is not a batchsim.engine.Engine subclass"):
        register("other", object)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'ref' is registered already, as ReferenceEngine"):
        register("ref", type("Impostor", (ReferenceEngine,), {}))
    register("ref", ReferenceEngine)  # the same class again: nothing changes
    register("Other", Other, extra="other")
    assert parse("other") == Registered("other", Other, "other")


def test_the_memory_check_asks_the_backends_class(registry, capsys):
    spec = batchsim.load("arm")
    per_world = ReferenceEngine.physics_memory(spec.mjmodel).per_world
    estimate = backends.estimate_memory(spec, "ref", 1000, ros=False)
    assert per_world > 0 and estimate.physics_per_world > per_world  # and the contract's host arrays
    assert estimate.device == 0 and estimate.host > 1000 * estimate.physics_per_world
    assert estimate.backend == "ref"

    class Unstated(ReferenceEngine):  # a backend that states no estimate runs unchecked, and is told so
        name = "unstated"
        physics_memory = None

    register("unstated", Unstated)
    assert backends.estimate_memory(spec, "unstated", 1000, ros=False) is None
    args = run_parser().parse_args(["--backend", "unstated", "--worlds", "2"])
    runner.check_memory(args, spec, parse("unstated"))
    assert capsys.readouterr().err == "batchsim: warning: the unstated backend states no memory estimate: not checked\n"


@pytest.mark.parametrize(
    "backend, package, compiles",
    [(Backend.CPU, "mujoco", False), (Backend.MJX, "jax", True), (Backend.WARP, "mujoco_warp", True)],
    ids=["cpu", "mjx", "warp"],
)
def test_the_shipped_backends_state_whether_their_first_period_compiles(backend, package, compiles):
    """mjx compiles and warp captures its program on the first period; cpu does not
    (the contract suite checks that a fleet over several devices says what its shards say)."""
    need(package)
    assert backend_class(backend).compiles_first_period is compiles
    assert ReferenceEngine.compiles_first_period is False
