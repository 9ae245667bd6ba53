"""Fast DDS's shared-memory transport, sized for the bridge's camera and lidar messages. No rclpy.

Fast DDS, ROS 2 Jazzy's default middleware, carries messages between processes of one host
through a shared-memory segment per participant (the publisher's), 512 KiB by default:
smaller than one 320x240 RGB-D frame pair (230 KB of RGB and 307 KB of depth). A publisher
that fills it invalidates buffers its readers have not taken yet, and reliable readers get
them again through repairs, or not at all. Measured on the 2-core machine (one process
publishing 16 worlds' 320x240 RGB and depth at 10 Hz, 320 messages/s, to one subscriber
process): 242 of 320 messages/s arrived, the publisher busy 0.24 of a core; with a 2 MiB
segment all 320 arrived, at 0.11 of a core.

So, where the plan has cameras or lidars and the user has not configured Fast DDS
(FASTRTPS_DEFAULT_PROFILES_FILE, FASTDDS_DEFAULT_PROFILES_FILE, FASTDDS_BUILTIN_TRANSPORTS,
a DEFAULT_FASTRTPS_PROFILES.xml in the working directory, or another RMW_IMPLEMENTATION),
the bridge's participants get a profile with Fast DDS's two default transports, UDPv4 and
shared memory, the segment sized for twice the sensor messages a worker may publish in one
control period (at least 4 MiB, at most 64 MiB, and all workers together at most a quarter
of /dev/shm): all its worlds' where the backend produces every world at once (warp), a
share of them where it spreads the worlds over the sensor's period (cpu, mjx).
Fast DDS takes the whole segment up front (a 1 GiB one took 1 GiB of /dev/shm at once),
so the cap is memory, not a guess. Only the publishers' side changes: subscribers keep
their own configuration, and other hosts still reach the bridge over UDP.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

from batchsim.loop.sampler import MAX_PENDING
from ros_bridge.sensor_topics import SensorPlan

PROFILES_FILE = "FASTRTPS_DEFAULT_PROFILES_FILE"  # what Fast DDS 2.x (ROS 2 Jazzy) reads
_USER_SETTINGS = (PROFILES_FILE, "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS")
_FAST_DDS = ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp")
MIN_SEGMENT = 4 << 20  # bytes
MAX_SEGMENT = 64 << 20
MESSAGE_OVERHEAD = 1024  # bytes per message beyond its payload: header, frame id, CDR, RTPS


def burst_bytes(sensors: SensorPlan, nworld: int, control_rate: float | None = None) -> int:
    """Bytes of sensor messages one worker of `nworld` worlds may publish in one control period:
    each camera's image, depth and camera_info and each lidar's scan, for every world where the
    backend produces them all at once (or `control_rate` is None), else for the worlds one
    period covers (SensorSampler spreads them over the sensor's period; up to MAX_PENDING + 1
    periods' renders can be handed out together)."""
    total = 0
    sensors_bytes = [(t.rate, t.camera.pixels * (3 + 4) + 3 * MESSAGE_OVERHEAD, True) for t in sensors.cameras]
    sensors_bytes += [(t.rate, t.lidar.nray * (12 if t.lidar.is_3d else 4) + MESSAGE_OVERHEAD, False) for t in sensors.lidars]
    for rate, per_world, camera in sensors_bytes:
        worlds = nworld
        if not sensors.batched and control_rate:
            phases = max(1, round(control_rate / rate))
            worlds = min(nworld, math.ceil(nworld / phases) * ((MAX_PENDING + 1) if camera else 1))
        total += worlds * per_world
    return total


def segment_bytes(
    sensors: SensorPlan, nworld: int, shm_total: int | None = None, nworker: int = 1, control_rate: float | None = None
) -> int:
    """The segment for each of `nworker` workers of up to `nworld` worlds: twice the burst, at
    least MIN_SEGMENT, at most MAX_SEGMENT, and all of them together at most a quarter of
    /dev/shm (`shm_total` bytes: writing past a full tmpfs kills the process)."""
    size = max(MIN_SEGMENT, 2 * burst_bytes(sensors, nworld, control_rate))
    cap = MAX_SEGMENT if shm_total is None else min(MAX_SEGMENT, max(MIN_SEGMENT, shm_total // (4 * max(1, nworker))))
    return int(min(size, cap))


def profile_xml(segment: int) -> str:
    """A Fast DDS profile: UDPv4 and shared memory (the default pair), the segment `segment` bytes."""
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- written by batchsim's ROS bridge (ros_bridge/transport.py): Fast DDS's default transports,
     the shared-memory segment sized for camera and lidar messages -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>batchsim_shm</transport_id>
        <type>SHM</type>
        <segment_size>{int(segment)}</segment_size>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>batchsim_udp</transport_id>
        <type>UDPv4</type>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="batchsim_bridge" is_default_profile="true">
      <rtps>
        <userTransports>
          <transport_id>batchsim_shm</transport_id>
          <transport_id>batchsim_udp</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def user_configured(environ: MutableMapping[str, str] | None = None, cwd: Path | None = None) -> str | None:
    """What says the user chose the middleware's configuration (a variable's name, a file), or None."""
    env = os.environ if environ is None else environ
    if env.get("RMW_IMPLEMENTATION", "") not in _FAST_DDS:
        return "RMW_IMPLEMENTATION"
    for name in _USER_SETTINGS:
        if env.get(name):
            return name
    default = (cwd or Path.cwd()) / "DEFAULT_FASTRTPS_PROFILES.xml"
    return str(default) if default.exists() else None


class TransportProfile:
    """The profile file for a fleet's bridge workers, or nothing where it is not needed.

    Args:
      sensors: the plan's cameras and lidars (None: no profile; joint states fit the default).
      worker_worlds: the worlds of each worker.
      control_rate: Hz, for the share of worlds a spreading backend produces per period.

    Attributes:
      path: the file (None: none written), removed by close().
      segment: its segment size in bytes (0: none).
    """

    def __init__(self, sensors: SensorPlan | None, worker_worlds: list[int], control_rate: float | None = None):
        self.path: Path | None = None
        self.segment = 0
        if sensors is None or not worker_worlds or user_configured() is not None:
            return
        try:
            stat = os.statvfs("/dev/shm")
            shm_total = stat.f_frsize * stat.f_blocks
        except OSError:
            shm_total = None
        self.segment = segment_bytes(sensors, max(worker_worlds), shm_total, len(worker_worlds), control_rate)
        fd, name = tempfile.mkstemp(prefix=f"batchsim_fastdds_{os.getpid()}_", suffix=".xml")
        with os.fdopen(fd, "w") as f:
            f.write(profile_xml(self.segment))
        self.path = Path(name)

    def apply(self, environ: MutableMapping[str, str]) -> None:
        """Point `environ` (a worker's environment, or this process's) at the profile."""
        if self.path is not None:
            environ[PROFILES_FILE] = str(self.path)

    def close(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)
            self.path = None
