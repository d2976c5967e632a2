"""Listening TCP sockets, read from /proc (what ``ss -ltnp`` shows, without needing iproute2)."""

from __future__ import annotations

import ipaddress
import os
import socket
import struct
from pathlib import Path

_LISTEN = "0A"


def _address(hex_ip: str) -> str:
    raw = bytes.fromhex(hex_ip)
    # /proc prints the address as 32-bit words in host byte order
    words = b"".join(struct.pack("=I", struct.unpack(">I", raw[i:i + 4])[0]) for i in range(0, len(raw), 4))
    return str(ipaddress.ip_address(words))


def listening() -> list[tuple[str, int, int]]:
    """``(address, port, socket inode)`` of every listening TCP socket of this network namespace."""
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if f[3] != _LISTEN:
                continue
            ip, port = f[1].split(":")
            out.append((_address(ip), int(port, 16), int(f[9])))
    return out


def socket_inodes(pid: int) -> set[int]:
    """Inodes of the sockets process ``pid`` holds (empty if it is gone)."""
    inodes = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return inodes
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(int(target[8:-1]))
    return inodes


def listening_of(pids) -> list[tuple[str, int]]:
    """``(address, port)`` of the listening sockets held by any of ``pids``."""
    inodes = set().union(*(socket_inodes(p) for p in pids)) if pids else set()
    return sorted({(addr, port) for addr, port, inode in listening() if inode in inodes})


def is_loopback(addr: str) -> bool:
    return ipaddress.ip_address(addr).is_loopback


def children(pid: int) -> list[int]:
    """PIDs whose parent is ``pid``."""
    out = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                stat = (proc / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(proc.name))
    return out


def alive(pid: int) -> bool:
    """``pid`` exists and is not a zombie (a reaped or zombie process serves nothing)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def can_connect(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=2):
            return True
    except OSError:
        return False
