"""A service's Zenoh session: where it listens and connects (BusConfig), opening it, and the
endpoints it really got.

Loopback by default: with no config file a session listens on tcp/127.0.0.1 only and multicast
scouting is off, so nothing is reachable from, or discovered on, the lab network unless a config
says so. Multicast scouting finds peers on the LAN without configuration; it is off by default so
that tests and two rigs on one network never join each other by accident. The link lease is 1 s
(keep-alives every 250 ms), so the death of a process is noticed within about a second.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Literal

import zenoh
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from bagit.common.bus.keys import check_name
from bagit.common.clock import ClockKind
from bagit.common.errors import BusError, first_line

_ENDPOINT_RE = re.compile(r"^[a-z][a-z0-9-]*/\S+$")
DEFAULT_ROUTER_PORT = 7447


class BusConfig(BaseModel):
    """Where a service's Zenoh session listens and connects, and on which rig.

    With `config_file` (a Zenoh json5 config) the file is the base and only the fields set
    explicitly here override it; without one, every field applies and the session stays on
    loopback. A file without listen endpoints also gets the loopback default.
    """

    model_config = ConfigDict(extra="forbid")

    rig: str = Field("default", description="rig name: the second chunk of every key, so rigs can share a network")
    mode: Literal["peer", "client", "router"] = "peer"
    connect: list[str] = Field(default_factory=list, description="endpoints to connect to, e.g. tcp/10.0.0.2:7447")
    listen: list[str] | None = Field(
        None, description="endpoints to listen on; None = tcp/127.0.0.1:0 (peer), tcp/127.0.0.1:7447 (router), none (client)"
    )
    multicast_scouting: bool = Field(False, description="discover peers by UDP multicast on the LAN (off: loopback tests, rig isolation)")
    config_file: Path | None = Field(None, description="a Zenoh json5 config used as the base")
    lease_ms: int = Field(1000, ge=100, le=60_000, description="link lease: a silent peer is declared dead after this")
    adminspace: bool = Field(False, description="answer queries on the @/ admin space (needed by `locators`)")
    tls_ca: Path | None = Field(None, description="CA certificate (PEM) that signs every identity on the rig")
    tls_cert: Path | None = Field(None, description="this service's certificate (PEM); its common name is its identity")
    tls_key: Path | None = Field(None, description="this service's private key (PEM), with tls_cert: mutual TLS")
    scouting_delay_ms: int | None = Field(
        None, ge=0, le=10_000, description="how long a peer's open waits for scouting; None = 0 without multicast, 500 with"
    )
    clock: ClockKind = Field("wall", description="wall: this host's clock (a real rig); sim: the simulator's, from sim/clock (lockstep)")

    @field_validator("rig")
    @classmethod
    def _rig(cls, v: str) -> str:
        return check_name(v, "rig name")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str] | None) -> list[str] | None:
        for e in v or []:
            if not _ENDPOINT_RE.match(e):
                raise ValueError(f"endpoint {e!r} is not '<proto>/<address>' (e.g. tcp/127.0.0.1:7447)")
        return v

    @model_validator(mode="after")
    def _tls_pair(self) -> BusConfig:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        return self

    def listen_endpoints(self, mode: str | None = None) -> list[str]:
        """The listen endpoints this config asks for (loopback unless set) in `mode` (default: self.mode)."""
        if self.listen is not None:
            return list(self.listen)
        mode = mode or self.mode
        if mode == "router":
            return [f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}"]
        if mode == "peer":
            return ["tcp/127.0.0.1:0"]
        return []

    def to_zenoh(self) -> zenoh.Config:
        """Build the zenoh.Config. Raises BusError for an unreadable or invalid config file."""
        explicit = self.model_fields_set
        if self.config_file is not None:
            try:
                zc = zenoh.Config.from_file(str(self.config_file))
            except (zenoh.ZError, OSError, ValueError) as e:
                raise BusError(f"zenoh config {self.config_file}: {first_line(e)}") from None
            file_listen = config_value(zc, "listen/endpoints")
            # zenoh's default listen (a dict per mode on [::]) means the file did not say: stay on loopback
            listen_unset = isinstance(file_listen, dict) or file_listen is None
            mode = self.mode if "mode" in explicit else (config_value(zc, "mode") or "peer")
        else:
            zc = zenoh.Config()
            explicit = set(type(self).model_fields)
            listen_unset = True
            mode = self.mode
        try:
            if "mode" in explicit:
                zc.insert_json5("mode", json.dumps(self.mode))
            if "connect" in explicit:
                zc.insert_json5("connect/endpoints", json.dumps(self.connect))
            if "listen" in explicit or listen_unset:
                zc.insert_json5("listen/endpoints", json.dumps(self.listen_endpoints(mode)))
            if "multicast_scouting" in explicit:
                zc.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
            if "lease_ms" in explicit:
                zc.insert_json5("transport/link/tx/lease", json.dumps(self.lease_ms))
            if "scouting_delay_ms" in explicit or "multicast_scouting" in explicit:
                delay = self.scouting_delay_ms if self.scouting_delay_ms is not None else (500 if self.multicast_scouting else 0)
                zc.insert_json5("scouting/delay", json.dumps(delay))
            if "tls_ca" in explicit and self.tls_ca is not None:
                zc.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(self.tls_ca)))
            if "tls_cert" in explicit and self.tls_cert is not None and self.tls_key is not None:
                # the same identity whether this end dials or listens; mutual: both ends show a certificate
                for side in ("connect", "listen"):
                    zc.insert_json5(f"transport/link/tls/{side}_certificate", json.dumps(str(self.tls_cert)))
                    zc.insert_json5(f"transport/link/tls/{side}_private_key", json.dumps(str(self.tls_key)))
                zc.insert_json5("transport/link/tls/enable_mtls", "true")
            if "adminspace" in explicit:
                zc.insert_json5("adminspace/enabled", json.dumps(self.adminspace))
        except (zenoh.ZError, ValueError) as e:
            raise BusError(f"zenoh config: {first_line(e)}") from None
        return zc


def config_value(zc: zenoh.Config, key: str) -> Any:
    """A value of a zenoh.Config, parsed (zenoh's get_json returns JSON text); None if absent."""
    try:
        return json.loads(zc.get_json(key))
    except (zenoh.ZError, ValueError, TypeError):
        return None


def open_session(cfg: BusConfig) -> zenoh.Session:
    """Open a Zenoh session for `cfg`. Raises BusError when Zenoh refuses (port taken, router absent...).

    A client whose config says `connect.timeout_ms: -1` (the deploy/ host configs) waits here
    until the router answers, which is what a service started at boot wants.
    """
    zenoh.try_init_log_from_env()
    zc = cfg.to_zenoh()
    try:
        return zenoh.open(zc)
    except zenoh.ZError as e:
        raise BusError(
            f"cannot open a zenoh {cfg.mode} session (listen {cfg.listen_endpoints()}, connect {cfg.connect}): {first_line(e)}"
        ) from None


def locators(session: zenoh.Session, timeout: float = 2.0) -> list[str]:
    """The endpoints `session` really listens on (port 0 resolved). Needs BusConfig(adminspace=True)."""
    zid = str(session.zid())
    for reply in session.get(f"@/{zid}/*", timeout=timeout):
        if reply.ok is None:
            continue
        try:
            info = json.loads(reply.ok.payload.to_bytes())
        except (ValueError, UnicodeDecodeError):
            continue
        if isinstance(info, dict) and isinstance(info.get("locators"), list):
            return [str(x) for x in info["locators"]]
    raise BusError(f"session {zid} did not report its locators (open it with BusConfig(adminspace=True))")



def parse_bus_config(data: dict[str, Any]) -> BusConfig:
    """Validate a bus config mapping; BusError naming the first bad field otherwise."""
    try:
        return BusConfig.model_validate(data)
    except ValidationError as e:
        first = e.errors()[0]
        where = ".".join(map(str, first["loc"])) or "bus"
        raise BusError(f"bus config: {where}: {first['msg'].removeprefix('Value error, ')}") from None
