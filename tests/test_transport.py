"""ros_bridge/transport.py: the Fast DDS profile the bridge's workers get for camera and lidar
messages, and when they get none. Plain Python: no rclpy, no DDS."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import batchsim
from ros_bridge.sensor_topics import sensor_plan
from ros_bridge.transport import (
    MAX_SEGMENT,
    MIN_SEGMENT,
    PROFILES_FILE,
    TransportProfile,
    burst_bytes,
    profile_xml,
    segment_bytes,
    user_configured,
)


def _plan(resolution: tuple[int, int]):
    sim = batchsim.make("rover", 1, "cpu", sensors={"sensors": {"camera_resolution": list(resolution)}})
    return sensor_plan(sim)


def test_the_segment_holds_twice_a_workers_burst_of_frames():
    plan = _plan((320, 240))
    assert not plan.batched  # cpu spreads the worlds over the sensor's period
    camera, scan = 320 * 240 * 7 + 3 * 1024, 360 * 4 + 1024  # RGB + depth + info; the scan
    assert burst_bytes(plan, 16) == 16 * (camera + scan)  # every world at once, as warp produces them
    assert segment_bytes(plan, 16) == 2 * 16 * (camera + scan)  # 17.3 MB: one pair is 537 KB, Fast DDS's default 512 KiB
    # at 100 Hz the 5 Hz camera covers 1 of 16 worlds a period (5 periods' renders may go out
    # together) and the 10 Hz lidar 2
    assert burst_bytes(plan, 16, control_rate=100.0) == 5 * camera + 2 * scan
    assert segment_bytes(_plan((16, 12)), 1) == MIN_SEGMENT
    assert segment_bytes(plan, 100_000) == MAX_SEGMENT  # Fast DDS takes all of it up front
    assert segment_bytes(plan, 16, shm_total=64 << 20) == 16 << 20  # a quarter of a 64 MiB /dev/shm
    assert segment_bytes(plan, 16, shm_total=256 << 20, nworker=8) == 8 << 20  # 8 workers share a quarter
    assert segment_bytes(plan, 16, shm_total=64 << 20, nworker=8) == MIN_SEGMENT  # never under the floor


def test_the_profile_keeps_fast_dds_default_transports():
    root = ET.fromstring(profile_xml(12345678))
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    kinds = {d.find("f:transport_id", ns).text: d.find("f:type", ns).text for d in root.iterfind(".//f:transport_descriptor", ns)}
    assert sorted(kinds.values()) == ["SHM", "UDPv4"]  # other hosts still reach the bridge over UDP
    assert root.find(".//f:segment_size", ns).text == "12345678"
    participant = root.find(".//f:participant", ns)
    assert participant.get("is_default_profile") == "true"
    assert [t.text for t in participant.iterfind(".//f:userTransports/f:transport_id", ns)] == list(kinds)


def test_a_user_configuration_of_the_middleware_wins(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in (PROFILES_FILE, "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS", "RMW_IMPLEMENTATION"):
        monkeypatch.delenv(name, raising=False)
    assert user_configured() is None
    for name, value in (
        ("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp"),
        (PROFILES_FILE, "/etc/mine.xml"),
        ("FASTDDS_BUILTIN_TRANSPORTS", "LARGE_DATA"),
    ):
        with monkeypatch.context() as m:
            m.setenv(name, value)
            assert user_configured() == name
            assert TransportProfile(_plan((320, 240)), [16]).path is None
    (tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml").write_text("<dds/>")
    assert user_configured() == str(tmp_path / "DEFAULT_FASTRTPS_PROFILES.xml")


def test_the_profile_file_is_written_pointed_at_and_removed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in (PROFILES_FILE, "FASTDDS_DEFAULT_PROFILES_FILE", "FASTDDS_BUILTIN_TRANSPORTS", "RMW_IMPLEMENTATION"):
        monkeypatch.delenv(name, raising=False)
    assert TransportProfile(None, [16]).path is None  # no cameras or lidars: Fast DDS's default fits
    profile = TransportProfile(_plan((320, 240)), [16, 15])
    assert profile.path.exists() and f"<segment_size>{profile.segment}</segment_size>" in profile.path.read_text()
    env: dict[str, str] = {}
    profile.apply(env)
    assert env == {PROFILES_FILE: str(profile.path)}
    path = profile.path
    profile.close()
    assert not path.exists() and profile.path is None
