"""CRTP, the Crazyflie's radio protocol: the ports, channels and packet layouts this project speaks.

One CRTP packet is a header byte ``port << 4 | 3 << 2 | channel`` and up to 30 bytes of
payload; cflib's UDP driver carries exactly one per datagram. The layouts below are
those cflib 0.1.34 sends to firmware of CRTP protocol version 12 (read from cflib's
source and the firmware's documentation); the simulated fleet decodes them with these
functions, and the tests check the decoded values against what cflib was asked to send.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

MAX_PAYLOAD = 30
PROTOCOL_VERSION = 12  # >= 12: arming and emergency stop through the supervisor port

# ports
CONSOLE, PARAM, COMMANDER, MEM, LOGGING, LOCALIZATION = 0x0, 0x2, 0x3, 0x4, 0x5, 0x6
COMMANDER_GENERIC, SETPOINT_HL, SUPERVISOR, PLATFORM, LINKCTRL = 0x7, 0x8, 0x9, 0xD, 0xF

# channels and commands, per port
TOC_CHANNEL = 0
TOC_ITEM_V2, TOC_INFO_V2 = 2, 3  # TOC commands (log and param ports)
PARAM_READ, PARAM_WRITE, PARAM_MISC = 1, 2, 3
LOG_SETTINGS, LOG_DATA = 1, 2
LOG_DELETE, LOG_START, LOG_STOP, LOG_RESET, LOG_CREATE_V2, LOG_APPEND_V2 = 2, 3, 4, 5, 6, 7
MEM_INFO, MEM_INFO_NBR = 0, 1
GENERIC_SETPOINT, GENERIC_META = 0, 1
SETPOINT_STOP, SETPOINT_VELOCITY_WORLD, SETPOINT_HOVER, SETPOINT_FULL_STATE, SETPOINT_POSITION = 0, 8, 10, 6, 7
META_NOTIFY_SETPOINT_STOP = 0
LOC_POSITION, LOC_GENERIC = 0, 1
LOC_EXT_POSE, LOC_EMERGENCY_STOP = 8, 3
HL_STOP, HL_GO_TO, HL_TAKEOFF_2, HL_LAND_2, HL_GO_TO_2 = 3, 4, 7, 8, 12
SUPERVISOR_INFO, SUPERVISOR_COMMAND = 0, 1
SUP_ARM, SUP_EMERGENCY_STOP, SUP_EMERGENCY_STOP_WATCHDOG, SUP_GET_STATE = 0x01, 0x03, 0x04, 0x0C
SUP_RESPONSE = 0x80  # the supervisor's answers carry the request's command with this bit set
# supervisor state bits (cflib's Supervisor.STATES order)
BIT_CAN_BE_ARMED, BIT_IS_ARMED, BIT_CAN_FLY, BIT_IS_FLYING, BIT_TUMBLED, BIT_LOCKED, BIT_CRASHED = 0, 1, 3, 4, 5, 6, 7
BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 8, 9, 10
PLATFORM_COMMAND, PLATFORM_VERSION = 0, 1
PLATFORM_REQUEST_ARMING, VERSION_GET_PROTOCOL, VERSION_GET_FIRMWARE = 1, 0, 1
LINK_ECHO, LINK_SOURCE = 0, 1
LINK_SOURCE_NAME = b"Bitcraze Crazyflie"

# TOC element types: (code, struct format)
PARAM_TYPES = {"uint8_t": (0x08, "<B"), "uint16_t": (0x09, "<H"), "uint32_t": (0x0A, "<L"), "float": (0x06, "<f")}
LOG_TYPES = {0x01: "<B", 0x02: "<H", 0x03: "<L", 0x04: "<b", 0x05: "<h", 0x06: "<i", 0x07: "<f", 0x08: "<e"}
LOG_TYPE_CODE = {"uint8_t": 0x01, "uint16_t": 0x02, "uint32_t": 0x03, "float": 0x07}


def header(port: int, channel: int) -> int:
    """The header byte of a packet on ``port`` and ``channel`` (link bits 3 << 2 set, as cflib does)."""
    return (port & 0x0F) << 4 | 3 << 2 | (channel & 0x03)


def split_header(byte: int) -> tuple[int, int]:
    """(port, channel) of a header byte."""
    return (byte >> 4) & 0x0F, byte & 0x03


def packet(port: int, channel: int, payload: bytes) -> bytes:
    """A whole datagram: header and payload (at most 30 bytes)."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"CRTP payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return bytes([header(port, channel)]) + payload


def toc_entry(ident: int, type_code: int, group: str, name: str) -> bytes:
    """A TOC item answer (v2): command, 16-bit id, type/metadata byte, "group\\0name\\0"."""
    return struct.pack("<BHB", TOC_ITEM_V2, ident, type_code) + group.encode() + b"\0" + name.encode() + b"\0"


def toc_info(count: int, crc: int) -> bytes:
    """A TOC info answer (v2): command, 16-bit item count, 32-bit CRC (cflib's TOC cache key)."""
    return struct.pack("<BHI", TOC_INFO_V2, count, crc)


def decompress_quaternion(comp: int) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a 32-bit compressed one (the firmware's quatcompress.h layout):
    2 bits name the largest component, which is left out and recovered from the unit norm; each of the
    other three is a sign bit and 9 bits of magnitude scaled by 1/sqrt(2)."""
    largest = comp >> 30
    q = [0.0, 0.0, 0.0, 0.0]
    sum_squares = 0.0
    for i in (3, 2, 1, 0):
        if i == largest:
            continue
        mag = (comp & 0x1FF) / 511.0 * math.sqrt(0.5)
        negative = (comp >> 9) & 1
        comp >>= 10
        q[i] = -mag if negative else mag
        sum_squares += mag * mag
    q[largest] = math.sqrt(max(0.0, 1.0 - sum_squares))
    return q[0], q[1], q[2], q[3]


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (radians, counter-clockwise about +z) of a quaternion (x, y, z, w)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass(frozen=True)
class Setpoint:
    """A decoded low-level setpoint: kind ('position', 'full_state', 'velocity', 'hover', 'stop'), position
    (x, y, z) m, velocity (vx, vy, vz) m/s, acceleration m/s^2 and yaw in degrees where the kind carries them."""

    kind: str
    pos: tuple[float, float, float] | None = None
    vel: tuple[float, float, float] | None = None
    yaw_deg: float | None = None
    acc: tuple[float, float, float] | None = None


def decode_setpoint(payload: bytes) -> Setpoint:
    """A generic-commander setpoint (port 7, channel 0).

    position: ``<Bffff`` type, x, y, z, yaw (degrees); full state: ``<BhhhhhhhhhIhhh`` with
    position in mm, velocity in mm/s, acceleration in mm/s^2 (int16), a compressed
    quaternion and body rates; velocity (world) and hover: ``<Bffff``; stop: type only.
    """
    kind = payload[0]
    if kind == SETPOINT_POSITION:
        _, x, y, z, yaw = struct.unpack("<Bffff", payload[:17])
        return Setpoint("position", (x, y, z), None, yaw)
    if kind == SETPOINT_FULL_STATE:
        v = struct.unpack("<BhhhhhhhhhIhhh", payload[:29])
        yaw = math.degrees(yaw_of_quaternion(*decompress_quaternion(v[10])))
        return Setpoint(
            "full_state",
            (v[1] / 1000, v[2] / 1000, v[3] / 1000),
            (v[4] / 1000, v[5] / 1000, v[6] / 1000),
            yaw,
            (v[7] / 1000, v[8] / 1000, v[9] / 1000),
        )
    if kind in (SETPOINT_VELOCITY_WORLD, SETPOINT_HOVER):
        _, a, b, c, d = struct.unpack("<Bffff", payload[:17])
        return Setpoint("velocity" if kind == SETPOINT_VELOCITY_WORLD else "hover", None, (a, b, c), d)
    if kind == SETPOINT_STOP:
        return Setpoint("stop")
    return Setpoint(f"type{kind}")


@dataclass(frozen=True)
class HighLevel:
    """A decoded high-level commander command: 'takeoff', 'land', 'go_to' or 'stop'; target (x, y, z)
    or height in z, yaw in radians (ignored when ``current_yaw``), duration s, relative."""

    kind: str
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    duration: float = 0.0
    relative: bool = False
    current_yaw: bool = False


def decode_high_level(payload: bytes) -> HighLevel:
    """A high-level commander packet (port 8): takeoff/land 2 ``<BBff?f`` (command, group mask, height, yaw,
    use-current-yaw, duration), go_to 2 ``<BBBBfffff`` (command, group, relative, linear, x, y, z, yaw, duration),
    go_to ``<BBBfffff``, stop ``<BB``."""
    cmd = payload[0]
    if cmd in (HL_TAKEOFF_2, HL_LAND_2):
        _, _, height, yaw, current, duration = struct.unpack("<BBff?f", payload[:15])
        kind = "takeoff" if cmd == HL_TAKEOFF_2 else "land"
        return HighLevel(kind, (0.0, 0.0, height), yaw, duration, current_yaw=bool(current))
    if cmd == HL_GO_TO_2:
        _, _, rel, _, x, y, z, yaw, duration = struct.unpack("<BBBBfffff", payload[:24])
        return HighLevel("go_to", (x, y, z), yaw, duration, bool(rel))
    if cmd == HL_GO_TO:
        _, _, rel, x, y, z, yaw, duration = struct.unpack("<BBBfffff", payload[:23])
        return HighLevel("go_to", (x, y, z), yaw, duration, bool(rel))
    if cmd == HL_STOP:
        return HighLevel("stop")
    return HighLevel(f"command{cmd}")


def decode_extpos(payload: bytes) -> tuple[float, float, float]:
    """External position (port 6, channel 0): ``<fff`` x, y, z in metres."""
    x, y, z = struct.unpack("<fff", payload[:12])
    return x, y, z


def decode_extpose(payload: bytes) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """External pose (port 6, channel 1, type 8): ``<Bfffffff`` type, x, y, z, qx, qy, qz, qw."""
    v = struct.unpack("<Bfffffff", payload[:29])
    return (v[1], v[2], v[3]), (v[4], v[5], v[6], v[7])


def log_data(block: int, timestamp_ms: int, values: list[tuple[int, float]]) -> bytes:
    """A log data packet (port 5, channel 2): block id, 24-bit timestamp (ms), values packed by fetch type."""
    body = struct.pack("<B", block) + (timestamp_ms & 0xFFFFFF).to_bytes(3, "little")
    for fetch, value in values:
        fmt = LOG_TYPES[fetch]
        body += struct.pack(fmt, int(value) if fmt not in ("<f", "<e") else value)
    return body
