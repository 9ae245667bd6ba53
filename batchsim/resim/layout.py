"""What a recording's inputs hold, and how they are written: the row layout of `/batchsim/inputs`
and `/batchsim/starts`, the model's bytes and hash, and the std_msgs/Float64MultiArray CDR both
topics use (packed and read here with NumPy: the recorder and `batchsim resim` need no rclpy).

A message's `layout.data_offset` values come first (its header: period number, sim time, physics
steps), then `dim[0].size` rows of `dim[1].size` values.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import struct

import mujoco
import numpy as np

INPUTS_TOPIC = "/batchsim/inputs"
STARTS_TOPIC = "/batchsim/starts"
EVENTS_TOPIC = "/batchsim/controller_inputs"  # std_msgs/String: one JSON document per input (controller_events.py)
EVENTS_TYPE = "std_msgs/msg/String"
MSG_TYPE = "std_msgs/msg/Float64MultiArray"
MODEL_ATTACHMENT = "batchsim/model.mjb"
METADATA = "batchsim_resim"  # the MCAP metadata record naming the layout
HEADER = 3  # period number, sim time, physics steps
_CDR_LE = b"\x00\x01\x00\x00"


@dataclasses.dataclass(frozen=True)
class ResimNames:
    """Where one group's re-simulation facts are in a file: its three topics and its model's
    attachment. A fleet of one group has the plain names; in a fleet of several groups (several
    models, batchsim.fleet.groups) each group has its own, and its METADATA record says which."""

    inputs: str
    starts: str
    events: str
    model: str


def resim_names(group: str = "") -> ResimNames:
    """The names of `group`'s facts ("": a fleet of one group)."""
    if not group:
        return ResimNames(INPUTS_TOPIC, STARTS_TOPIC, EVENTS_TOPIC, MODEL_ATTACHMENT)
    base = f"/batchsim/{group}"
    return ResimNames(f"{base}/inputs", f"{base}/starts", f"{base}/controller_inputs", f"batchsim/{group}/model.mjb")


@dataclasses.dataclass(frozen=True)
class InputsLayout:
    """The columns of a recording's input and start rows.

    Attributes:
      nu: ctrl values per world.
      base_velocity: whether a BaseVelocityPlugin's held target (3) follows ctrl.
      nbody: bodies of xfrc_applied (6 each) after those, where an ExternalWrenchPlugin runs; 0: none.
      nstate: values of mjSTATE_INTEGRATION.
      params: each varied model field and its shape (world_params' order), in start rows after the state.
      held_base: the free joint's qposadr and dofadr whose velocity the BaseVelocityPlugin holds; (-1, -1): none.
      ncommand: command interface values per world, last in an input row: `command` as the
        controllers (and the bridge's plain commands) left it for write().
    """

    nu: int
    base_velocity: bool
    nbody: int
    nstate: int
    params: tuple[tuple[str, tuple[int, ...]], ...] = ()
    held_base: tuple[int, int] = (-1, -1)
    ncommand: int = 0

    @property
    def input_width(self) -> int:
        """An input row: frozen (0/1), ctrl, the plugins' values, the command interfaces."""
        return 1 + self.nu + 3 * self.base_velocity + 6 * self.nbody + self.ncommand

    @property
    def start_width(self) -> int:
        """A start row: the world's number, its draw number, whether it starts afresh (the run's
        first period or a reset: its controllers start afresh too), its state, its model values."""
        return 3 + self.nstate + sum(int(np.prod(shape)) for _, shape in self.params)

    def input_row(self, frozen: np.ndarray, inputs: dict[str, np.ndarray]) -> np.ndarray:
        """(n, input_width) rows from the contract's physics_inputs and the frozen flags."""
        parts = [frozen.astype(np.float64)[:, None], inputs["ctrl"]]
        if self.base_velocity:
            parts.append(inputs["base_velocity"])
        if self.nbody:
            parts.append(inputs["xfrc_applied"])
        if self.ncommand:
            parts.append(inputs["command"])
        return np.concatenate(parts, axis=1)

    def split_inputs(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """input rows (n, input_width) -> frozen (n,) bool, ctrl (n, nu), base_velocity (n, 3), xfrc_applied (n, nbody, 6)."""
        out = {"frozen": rows[:, 0] != 0, "ctrl": rows[:, 1 : 1 + self.nu]}
        at = 1 + self.nu
        if self.base_velocity:
            out["base_velocity"], at = rows[:, at : at + 3], at + 3
        if self.nbody:
            out["xfrc_applied"], at = rows[:, at : at + 6 * self.nbody].reshape(len(rows), self.nbody, 6), at + 6 * self.nbody
        if self.ncommand:
            out["command"] = rows[:, at : at + self.ncommand]
        return out

    def start_row(
        self, worlds: np.ndarray, draws: np.ndarray, fresh: np.ndarray, state: np.ndarray, params: dict[str, np.ndarray]
    ) -> np.ndarray:
        """(n, start_width) rows: world numbers, draw numbers, fresh flags, mjSTATE_INTEGRATION
        states, model values."""
        n = len(worlds)
        flat = [params[f].reshape(n, -1) for f, _ in self.params]
        head = np.stack([np.asarray(worlds, np.float64), np.asarray(draws, np.float64), np.asarray(fresh, np.float64)], 1)
        return np.concatenate([head, state, *flat], axis=1)

    def split_start(self, row: np.ndarray) -> tuple[int, int, bool, np.ndarray, dict[str, np.ndarray]]:
        """A start row -> (world, draw number, fresh, state, field -> value)."""
        at = 3 + self.nstate
        params = {}
        for field, shape in self.params:
            size = int(np.prod(shape))
            params[field], at = row[at : at + size].reshape(shape), at + size
        return int(row[0]), int(row[1]), bool(row[2]), row[3 : 3 + self.nstate], params

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, text: str) -> InputsLayout:
        d = json.loads(text)
        d["params"] = tuple((f, tuple(shape)) for f, shape in d["params"])
        d["held_base"] = tuple(d["held_base"])
        return cls(**d)


def layout_of(
    model: mujoco.MjModel,
    inputs: dict[str, np.ndarray],
    params: dict[str, np.ndarray],
    held_base: tuple[int, int] = (-1, -1),
    ncommand: int = 0,
) -> InputsLayout:
    """The layout of a system's rows, from one world's physics_inputs and world_params, the
    held base's (qposadr, dofadr) where a BaseVelocityPlugin runs, and its command interfaces."""
    return InputsLayout(
        held_base=held_base,
        ncommand=ncommand,
        nu=int(model.nu),
        base_velocity="base_velocity" in inputs,
        nbody=int(model.nbody) if "xfrc_applied" in inputs else 0,
        nstate=int(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)),
        params=tuple((f, tuple(v.shape[1:])) for f, v in params.items() if f != "start_qpos"),
    )


def effort_sources(state_columns) -> dict[str, list]:
    """Where each joint's effort is read from, as a recording keeps it (its metadata's `effort`):
    joint -> [field (StateSource's value), index, sign], from the spec's `<joint>/effort` state
    columns (batchsim.model.spec.StateColumn)."""
    return {c.name.removesuffix("/effort"): [c.source.value, c.index, c.sign] for c in state_columns if c.name.endswith("/effort")}


def model_bytes(model: mujoco.MjModel) -> bytes:
    """The compiled model as MuJoCo's binary MJB: exactly the model, meshes and all."""
    buf = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return buf.tobytes()


def model_hash(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def load_model(data: bytes) -> mujoco.MjModel:
    """An MJB's model (model_bytes' inverse)."""
    return mujoco.MjModel.from_binary_path("model.mjb", {"model.mjb": data})


# --- std_msgs/msg/String and Float64MultiArray in CDR (little endian) ---
def pack_string(text: str) -> bytes:
    """A std_msgs/String."""
    data = text.encode() + b"\x00"
    return _CDR_LE + struct.pack("<I", len(data)) + data


def unpack_string(data: bytes) -> str:
    (length,) = struct.unpack_from("<I", data, 4)
    return data[8 : 8 + length - 1].decode()



def pack(header: np.ndarray, rows: np.ndarray, labels: tuple[str, str] = ("worlds", "values")) -> bytes:
    """A Float64MultiArray: `header` (data_offset values) then `rows` (n, width), row-major."""
    n, width = rows.shape
    out = bytearray(_CDR_LE)
    out += struct.pack("<I", 2)
    for label, size, stride in ((labels[0], n, n * width), (labels[1], width, width)):
        text = label.encode() + b"\x00"
        out += struct.pack("<I", len(text)) + text
        out += b"\x00" * (-(len(out) - 4) % 4)
        out += struct.pack("<II", size, stride)
    out += struct.pack("<II", len(header), len(header) + n * width)
    out += b"\x00" * (-(len(out) - 4) % 8)
    out += np.asarray(header, "<f8").tobytes() + np.ascontiguousarray(rows, "<f8").tobytes()
    return bytes(out)


def unpack(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A Float64MultiArray of pack's shape -> (header, rows (n, width)). ValueError if it is not one."""
    if data[:4] != _CDR_LE:
        raise ValueError("not a little-endian CDR message")
    at = 4
    (ndim,) = struct.unpack_from("<I", data, at)
    at += 4
    sizes = []
    for _ in range(ndim):
        (length,) = struct.unpack_from("<I", data, at)
        at += 4 + length
        at += -(at - 4) % 4
        size, _ = struct.unpack_from("<II", data, at)
        sizes.append(size)
        at += 8
    offset, count = struct.unpack_from("<II", data, at)
    at += 8
    at += -(at - 4) % 8
    values = np.frombuffer(data, "<f8", count, at)
    if ndim != 2 or count != offset + sizes[0] * sizes[1]:
        raise ValueError(f"a Float64MultiArray of {ndim} dimensions and {count} values is no batchsim input message")
    return values[:offset].copy(), values[offset:].reshape(sizes[0], sizes[1]).copy()
