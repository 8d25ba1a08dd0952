"""What the panel's buttons drive: the rig's run control and emergency stop.

The dashboard only knows this interface, so it runs and is tested without Zenoh; the Zenoh
implementation (bagit.dashboard.node.ZenohRunLink) asks run/control and puts on estop.

`start` takes a bundled scenario's name or a validated scenario document (a dict), the
parameter overrides (MethodParams fields) for that run and its controller (None: the rig's
default); it returns the coordinator's reply.
`estop` must return at once: it is called from the E-STOP button's handler and nothing else is
done before it. Failures raise a BagItError (e.g. BusError when no coordinator answers).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from bagit.common.messages import RunControlReply


@runtime_checkable
class RunLink(Protocol):
    def start(self, scenario: str | dict[str, Any], params: dict[str, Any], controller: str | None = None) -> RunControlReply: ...

    def stop(self) -> RunControlReply: ...

    def reset(self) -> RunControlReply: ...

    def estop(self, reason: str) -> None: ...

    def release_estop(self, reason: str) -> None: ...
