"""DDS network defaults of every rclpy process of the package: loopback only unless asked otherwise.

Fast DDS (``rmw_fastrtps_cpp``, the RMW of the PyPI rclpy wheels and ROS 2 Jazzy's default):
a profile given by ``FASTRTPS_DEFAULT_PROFILES_FILE`` plus
``ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT``. Out of the box Fast DDS discovers by
multicast on every interface; with :data:`FASTDDS_LOOPBACK_PROFILE` (UDPv4 transport
white-listed to 127.0.0.1, no built-in transports, unicast discovery to 127.0.0.1 on 60
participant ports) every datagram goes to 127.0.0.1 (traced: ``test/test_loopback.py``).
The range decides what rmw_fastrtps adds to the profile: ``SYSTEM_DEFAULT`` adds nothing;
``SUBNET`` (rclpy's default) adds the SPDP multicast announcements (to 239.255.0.1, on
``lo``); ``LOCALHOST`` adds a second loopback transport, so every sample is sent twice
(docs/security.md).

A user's own Fast DDS profile always wins; a configured interface (``HDRQN_DDS_INTERFACE``)
replaces loopback by that interface, with multicast discovery on
it. Another RMW chosen by ``RMW_IMPLEMENTATION`` keeps its own network settings.
"""
from __future__ import annotations

import fcntl
import os
import socket
import struct
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

INTERFACE_ENV = "HDRQN_DDS_INTERFACE"
"""The environment variable naming the network interface for DDS (unset: loopback only);
``hdrqn up --interface`` sets it for the nodes it starts."""


class NetworkConfigError(ValueError):
    """A network setting that cannot be used: an interface without IPv4, a Fast DDS profile
    that is missing or not XML."""

SOCKET_BUFFER_BYTES = 4 * 1024 * 1024
"""Fast DDS's UDP socket buffers (send and receive), in both profiles. With the system's
default (about 208 KiB) a batched group's samples (``num_envs`` 16: 93 KB observations,
186 KB subgoal images, each several 64 KB datagrams) overflow the receive buffer and the lost
fragments wait for a heartbeat (docs/topics.md, "Batched groups", has the figures). The kernel caps the size at ``net.core.rmem_max`` / ``wmem_max``."""
LOOPBACK = "lo"
MAX_PARTICIPANTS = 60
"""Unicast discovery ports probed on loopback (participant indices 0..59, the loopback
profile's ``maxInitialPeersRange``): one participant per process, so at most this many node
processes per machine and domain."""
FASTDDS_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
"""Where Fast DDS 2.x (Jazzy) and 3.x read the path of a default XML profile."""
FASTDDS_LOOPBACK_PROFILE = Path(__file__).with_name("fastdds_loopback.xml")


def interface_address(interface: str) -> str:
    """The IPv4 address of the network interface ``interface`` (e.g. ``eth0``); a
    :class:`NetworkConfigError` naming it when there is no such interface or it has no IPv4."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            request = struct.pack("256s", interface.encode()[:15])
            reply = fcntl.ioctl(sock.fileno(), 0x8915, request)  # SIOCGIFADDR
        except OSError as exc:
            raise NetworkConfigError(f"{INTERFACE_ENV}={interface!r}: no IPv4 address on such an interface "
                                 f"({exc.strerror})") from None
    return socket.inet_ntoa(reply[20:24])


def fastdds_interface_profile(address: str) -> str:
    """A Fast DDS profile that uses only the interface with IPv4 ``address``, discovering by
    multicast on it."""
    return ('<?xml version="1.0" encoding="UTF-8"?>\n'
            '<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"><profiles>'
            "<transport_descriptors><transport_descriptor><transport_id>hdrqn_udp</transport_id>"
            f"<type>UDPv4</type><sendBufferSize>{SOCKET_BUFFER_BYTES}</sendBufferSize>"
            f"<receiveBufferSize>{SOCKET_BUFFER_BYTES}</receiveBufferSize>"
            f"<interfaceWhiteList><address>{address}</address></interfaceWhiteList>"
            "</transport_descriptor></transport_descriptors>"
            '<participant profile_name="hdrqn_interface" is_default_profile="true"><rtps>'
            "<userTransports><transport_id>hdrqn_udp</transport_id></userTransports>"
            "<useBuiltinTransports>false</useBuiltinTransports></rtps></participant>"
            "</profiles></dds>\n")


def _write_once(name: str, text: str) -> str:
    """``text`` as the file ``name`` in the temporary directory (replaced atomically when it
    differs, so processes starting side by side never read half a file); returns its path."""
    path = Path(tempfile.gettempdir()) / name
    if not path.exists() or path.read_text() != text:
        handle, partial = tempfile.mkstemp(prefix=name, dir=path.parent)
        with os.fdopen(handle, "w") as out:
            out.write(text)
        os.replace(partial, path)
    return str(path)


def _is_ours(path: str) -> bool:
    return Path(path).resolve() == FASTDDS_LOOPBACK_PROFILE.resolve()


def check_fastdds_profile(path: str, variable: str) -> None:
    """A :class:`NetworkConfigError` naming ``path`` (from ``variable``) unless it is a readable XML
    file whose root is Fast DDS's ``<dds>`` or ``<profiles>``."""
    try:
        root = ET.parse(path).getroot()
    except OSError as exc:
        raise NetworkConfigError(f"{variable}={path}: cannot read the Fast DDS profile ({exc.strerror})") from None
    except ET.ParseError as exc:
        raise NetworkConfigError(f"{variable}={path}: the Fast DDS profile is not valid XML ({exc})") from None
    if root.tag.rpartition("}")[2] not in ("dds", "profiles"):
        raise NetworkConfigError(f"{variable}={path}: the Fast DDS profile's root element is <{root.tag}>, "
                             "not <dds> or <profiles>")


def check_user_fastdds_profile(environ: os._Environ | dict = os.environ) -> None:
    """A :class:`NetworkConfigError` naming the file if a Fast DDS profile the user set (not ours)
    does not exist or does not parse: what each rclpy node would exit with, asked up front."""
    for variable in FASTDDS_PROFILE_VARIABLES:
        if environ.get(variable) and not _is_ours(environ[variable]):
            check_fastdds_profile(environ[variable], variable)


def apply_rmw_network_defaults(interface: str | None, environ: os._Environ | dict = os.environ) -> str:
    """Before ``rclpy.init``: point the RMW at our network defaults unless the user configured
    their own; returns a one-line description of what the RMW will use.

    ``interface`` (``$HDRQN_DDS_INTERFACE``) None or ``"lo"``: loopback only. A Fast DDS profile the
    user names is checked (it must exist and parse) and kept. An RMW other than Fast DDS
    (``RMW_IMPLEMENTATION``) is left to its own settings."""
    rmw = environ.get("RMW_IMPLEMENTATION", "") or "rmw_fastrtps_cpp"
    if "fastrtps" not in rmw:
        return f"{rmw} with its own network settings (the loopback-only default covers Fast DDS)"
    for variable in FASTDDS_PROFILE_VARIABLES:
        if environ.get(variable) and not _is_ours(environ[variable]):  # ours: inherited from `hdrqn up`, a test
            check_fastdds_profile(environ[variable], variable)
            if interface is None:
                return f"{rmw} with the user's profile {environ[variable]}"
    if interface in (None, LOOPBACK):
        profile = str(FASTDDS_LOOPBACK_PROFILE)
        # the profile exactly as written: SUBNET would add multicast SPDP, LOCALHOST a duplicate transport
        environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT")
        where = "loopback only"
    else:
        address = interface_address(interface)
        profile = _write_once(f"hdrqn-fastdds-{address}.xml", fastdds_interface_profile(address))
        # an interface asked for wins over a range inherited from a loopback-only parent
        environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
        where = f"{interface} ({address})"
    for variable in FASTDDS_PROFILE_VARIABLES:
        environ[variable] = profile
    return f"{rmw} on {where}"
