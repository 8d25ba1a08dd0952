"""Linux network namespaces (`ip netns`): open sockets in another one from this process.

A thread's network namespace decides where the sockets it creates live; a socket keeps its
namespace afterwards. `entered_netns("NAME")` moves the calling thread into `/run/netns/NAME` for a
`with` block and back after it, so a process can listen on one network (the simulator's CR5s on a
robot LAN) while its other sockets stay on another (its Zenoh session). Threads started inside the
block inherit the namespace. Needs CAP_SYS_ADMIN (root) and Linux.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

NETNS_DIR = Path("/run/netns")  # where `ip netns add NAME` pins a namespace
CLONE_NEWNET = 0x40000000


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"setns: {os.strerror(err)}")


@contextmanager
def entered_netns(name: str) -> Iterator[None]:
    """This thread in network namespace `name` (an `ip netns` name) for the block; OSError if it cannot."""
    own = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
    try:
        target = os.open(NETNS_DIR / name, os.O_RDONLY)
    except OSError as e:
        os.close(own)
        raise OSError(e.errno, f"network namespace {name!r}: {e.strerror}") from None
    try:
        _setns(target)
        try:
            yield
        finally:
            _setns(own)
    finally:
        os.close(target)
        os.close(own)
