"""The policy controller a controllers YAML declares, read without running it: what the
training script trains on and `batchsim evaluate` evaluates."""

from __future__ import annotations

from pathlib import Path

from batchsim.controllers.base import Params
from batchsim.controllers.config import parse
from batchsim.controllers.policy.controller import PolicyController
from batchsim.controllers.policy.spec import PolicySpec, read_spec
from batchsim.types import ConfigurationError


def policy_controller_name(path: str | Path, name: str | None = None) -> str:
    """The name of the PolicyController `path` declares (`name` where it declares several);
    ConfigurationError naming the file where there is none, or several and no `name`."""
    config = parse(Path(path))
    found = [c.name for c in config.controllers if c.type == PolicyController.TYPE]
    if name is not None:
        if name not in found:
            raise ConfigurationError(
                f"{config.source}: no {PolicyController.TYPE} named {name!r} (policies: {', '.join(found) or 'none'})"
            )
        return name
    if len(found) != 1:
        which = "none" if not found else f"several ({', '.join(found)}): name one"
        raise ConfigurationError(
            f"{config.source}: a policy to evaluate: {PolicyController.TYPE} controllers: {which}"
        )
    return found[0]


def read_policy_yaml(
    path: str | Path, name: str | None = None, start_pose: dict[str, float] | None = None
) -> tuple[str, PolicySpec]:
    """(its name, its spec) from the YAML alone: the model's metadata is not read, so the YAML
    must give the joints and observations (a training writes the file it trains for)."""
    config = parse(Path(path))
    name = policy_controller_name(path, name)
    entry = next(c for c in config.controllers if c.name == name)
    params = Params(entry.params, where=config.source, controller=name)
    return name, read_spec(params, {}, start_pose or {})
