"""The Python and YAML blocks of the README and of every page in docs/, run the way a user
pastes them (issue: every snippet must run as shown), and the links between those pages.

Each Python block runs whole in a fresh interpreter from the repository root (a bridge block
on a private ROS domain, LOCALHOST); a block that needs what this machine lacks (PyTorch and
a CUDA GPU) is skipped, naming it. Each YAML block is read by the code that reads such a file:
a `sensors:` block loaded with the model it is shown beside, a PID file through
mujoco_ros2_control's reader. A block of another kind fails the test until it is taught here.
A test's id names the page and the line its block starts on (`docs/ros.md:120`). Every
relative link of a page (`[text](path)`, `[text](path#anchor)`, `[text](#anchor)`) must name
a file that exists and, with an anchor, a heading of that page as GitHub makes anchors.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_fleet import LOCALHOST, domain_id, release_domain

# over a few seconds each: `make test` runs them, `make quick` leaves them out
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
FENCE = re.compile(r"^( *)```(\w+)\n(.*?)^\1```$", re.S | re.M)
# the pages issue 46 asked for: the README is one page, docs/ holds the rest, docs/README.md indexes it
DOCS = "install cli python ros controllers real-robots fleets sensors randomization-and-rl recording-and-view scale performance development"
PAGES = ["README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))]


def blocks(lang: str) -> list[tuple[str, int, str]]:
    """Every fenced block of `lang` in every page: (page, the line its fence opens on, its text)."""
    out = []
    for page in PAGES:
        text = (ROOT / page).read_text()
        for m in FENCE.finditer(text):
            if m.group(2) == lang:
                indent = len(m.group(1))
                body = "\n".join(line[indent:] for line in m.group(3).splitlines())
                out.append((page, text.count("\n", 0, m.start()) + 1, body))
    return out


PYTHON = blocks("python")
YAML = blocks("yaml")


def test_every_page_is_read_and_the_blocks_are_all_there():
    """Every page of docs/ is read here and indexed (docs/README.md, the README's "Where to read
    next"), and no block was lost in the move out of the one long README: it had 6 Python and
    6 YAML blocks."""
    assert {f"docs/{name}.md" for name in DOCS.split()} | {"docs/README.md"} <= set(PAGES)
    index, readme = (ROOT / "docs" / "README.md").read_text(), (ROOT / "README.md").read_text()
    for page in PAGES[1:]:
        name = page.removeprefix("docs/")
        if name != "README.md":
            assert f"]({name})" in index, f"docs/README.md does not link {page}"
            assert f"]({page})" in readme, f"README.md's list of pages does not link {page}"
    assert len(PYTHON) >= 7 and len(YAML) >= 6, (len(PYTHON), len(YAML))
    assert any(page == "README.md" for page, _, _ in PYTHON), "the README drives the worlds from code"


@pytest.mark.parametrize("page, line, code", PYTHON, ids=[f"{page}:{n}" for page, n, _ in PYTHON])
def test_a_python_block_runs_as_shown(page, line, code):
    missing = [m for m in ("torch",) if re.search(rf"^import {m}\b", code, re.M) and importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"{page}:{line} needs {', '.join(missing)} (and a CUDA GPU)")
    domain = domain_id(98)
    try:
        env = {**os.environ, **LOCALHOST, "ROS_DOMAIN_ID": str(domain)}
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    finally:
        release_domain(domain)
    assert done.returncode == 0, f"{page}:{line}:\n{done.stderr[-3000:]}"


@pytest.mark.parametrize("page, line, text", YAML, ids=[f"{page}:{n}" for page, n, _ in YAML])
def test_a_yaml_block_is_read_as_shown(page, line, text, tmp_path):
    import batchsim
    from batchsim.model.params import nest_dotted, node_parameters, read_yaml
    from batchsim.pid import PidGains

    path = tmp_path / "block.yaml"
    path.write_text(text)
    if text.startswith("sensors:"):  # shown beside the rover (its camera, lidar site, wheel sensors)
        sim = batchsim.make("rover", 2, "cpu", sensors=str(path))
        sim.configure()
        assert "ring" in sim.sensors.lidars and sim.scan("ring").shape == (2, 360 * 16)
        sim.shutdown()
    elif "pid_gains" in text:
        params = nest_dotted(node_parameters(read_yaml(path), None, str(path)))
        for mode, joints in params["pid_gains"].items():
            assert mode in ("position", "velocity")
            for joint, values in joints.items():
                _, warnings = PidGains.from_params(values, f"pid_gains.{mode}.{joint}")
                assert not warnings, warnings
    elif "\nrobots:" in "\n" + text:  # a fleet file: its environment beside it as a floor of its own
        from batchsim.fleet import load_fleet

        (tmp_path / "warehouse.xml").write_text('<mujoco><worldbody><geom type="plane" size="5 5 .1"/></worldbody></mujoco>')
        (tmp_path / "arm.yaml").write_text(Path(batchsim.controllers.default_controllers("arm")).read_text())
        (tmp_path / "amr_sensors.yaml").write_text("sensors:\n  camera_resolution: [64, 48]\n")  # as for a rover alone
        spec = load_fleet(path)
        assert len(spec.robots) >= 2 and all(r.state.size for r in spec.robots)
        sized = [r for r in spec.robots if r.sensor_config is not None]
        assert sized and all(spec.sensor_config.cameras[r.prefix + "front_camera"].width == 64 for r in sized)
    elif "\ngroups:" in "\n" + text:  # a fleet of groups: its fleet files and environment beside it, as shipped
        from batchsim.fleet import load_fleet
        from batchsim.fleet.groups import read_groups

        fleets = Path(__file__).resolve().parent.parent / "examples" / "fleets"
        for name in ("arm_and_rover.yaml", "warehouse.xml"):
            (tmp_path / name).write_text((fleets / name).read_text())
        groups = read_groups(path).groups
        assert len(groups) >= 2 and all(len(load_fleet(g.fleet).robots) >= 2 for g in groups)
        assert [g.first_world for g in groups] == [sum(h.worlds for h in groups[:k]) for k in range(len(groups))]
    elif text.startswith("randomize:"):  # shown for the arm (its links, joints, position servos)
        sim = batchsim.make("arm", 3, "cpu", randomize=str(path))
        sim.configure()
        drawn = sim.world_params()
        assert {"body_mass", "geom_friction", "dof_damping", "actuator_gainprm", "opt.gravity", "start_qpos"} <= set(drawn)
        assert not np.array_equal(drawn["body_mass"][0], drawn["body_mass"][1])
        sim.shutdown()
    elif "\n  ros__parameters:\n    model: arm_reach.onnx" in text:  # the shipped policy's block, as shipped
        shipped = Path(__file__).resolve().parent.parent / "examples" / "policies" / "arm_reach.yaml"
        assert read_yaml(path)["arm_reach_controller"] == read_yaml(shipped)["arm_reach_controller"]
    else:
        pytest.fail(f"{page}:{line}: a YAML block of a kind tests/test_readme.py does not know how to read")


LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)\)")
CODE = re.compile(r"^( *)```.*?^\1```$|`[^`\n]*`", re.S | re.M)


def anchors(text: str) -> set[str]:
    """The anchors GitHub gives a page's headings: lower case, punctuation but `-` and `_`
    dropped, spaces as `-`; a repeated one gets `-1`, `-2`, ... (headings in code blocks are none)."""
    seen: dict[str, int] = {}
    out = set()
    for m in re.finditer(r"^#{1,6} +(.+?) *#* *$", re.sub(r"^( *)```.*?^\1```$", "", text, flags=re.S | re.M), re.M):
        slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return out


def links(page: str) -> list[tuple[int, str]]:
    """Every relative link of a page, outside code: (line, target)."""
    text = (ROOT / page).read_text()
    prose = CODE.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)  # blanked, lines kept
    return [
        (prose.count("\n", 0, m.start()) + 1, m.group(1))
        for m in LINK.finditer(prose)
        if not re.match(r"[a-z][a-z0-9+.-]*:", m.group(1))  # http:, https:, mailto: ...
    ]


def test_the_anchors_are_githubs():
    text = "# batchsim\n## The first fleet: from `batchsim --worlds 16` to moving arms\n## mujoco_ros2_control's robots, files and tests\n```bash\n# not a heading\n```\n## Notes\n## Notes\n"
    assert anchors(text) == {"batchsim", "the-first-fleet-from-batchsim---worlds-16-to-moving-arms", "mujoco_ros2_controls-robots-files-and-tests", "notes", "notes-1"}


@pytest.mark.parametrize("page", PAGES)
def test_every_relative_link_of_a_page_resolves(page):
    found = links(page)
    if page != "docs/README.md" and page.startswith("docs/"):
        assert found, f"{page} links no other page"
    broken = []
    for line, target in found:
        path, _, anchor = target.partition("#")
        file = ((ROOT / page).parent / path).resolve() if path else ROOT / page
        if not file.exists():
            broken.append(f"{page}:{line}: {target}: no file {os.path.relpath(file, ROOT)}")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file.read_text()):
            broken.append(f"{page}:{line}: {target}: {path or page} has no heading #{anchor}")
    assert not broken, "\n".join(broken)
