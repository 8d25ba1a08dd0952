"""The arm driver's own settings: how it talks to the controllers and how it streams.

The motion limits themselves live in the rig config (`bagit.common.rig.SafetyLimits`, one place
for every service); this model holds what only the driver needs: ServoP's `aheadtime` and
`gain`, time-outs, reconnect back-off, and how far a target may run ahead of the arm.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class DriverConfig(BaseModel):
    """Driver settings; the defaults suit the CR5 on a LAN and the simulated controllers."""

    model_config = ConfigDict(extra="forbid")

    servo_command: Literal["servop", "servoj"] = Field(
        "servop", description="ServoP (the controller's own IK) or ServoJ (IK here, bagit.common.cr5)"
    )
    check_reach: bool = Field(
        True, description="solve each ServoP target with bagit.common.cr5 first; unreachable: stop both arms smoothly"
    )
    servo_t_factor: float = Field(
        1.0, ge=1.0, le=2.0,
        description="ServoP's t as a multiple of the servo period: 1 reaches each target as the next arrives; "
        "a little more rides out a late cycle without the arm stopping in between",
    )
    aheadtime: float = Field(50.0, ge=20.0, le=100.0, description="ServoP/ServoJ aheadtime (Dobot's range 20..100)")
    gain: float = Field(500.0, ge=200.0, le=1000.0, description="ServoP/ServoJ gain (Dobot's range 200..1000)")
    halt_aheadtime: float = Field(
        100.0, ge=20.0, le=100.0,
        description="aheadtime of the ServoPs that brake to rest (hold, watchdog, fault): the controller follows the "
        "braking without its lag, so the arms are still sooner (on the simulated CR5: ~30 ms); `aheadtime` turns it off",
    )
    reply_timeout_s: float = Field(0.5, gt=0.0, le=10.0, description="a dashboard reply later than this is an error")
    connect_timeout_s: float = Field(1.0, gt=0.0, le=30.0)
    feedback_timeout_s: float = Field(
        0.2, gt=0.0, le=5.0, description="no feedback packet for this long: the stream is lost, both arms stop"
    )
    reconnect_initial_s: float = Field(0.05, gt=0.0, le=5.0, description="first reconnect back-off")
    reconnect_max_s: float = Field(2.0, gt=0.0, le=60.0, description="back-off doubles up to this")
    enable_timeout_s: float = Field(2.0, gt=0.0, le=30.0, description="bring-up waits this long for the arm to report enabled")
    stop_timeout_s: float = Field(2.0, gt=0.0, le=30.0, description="shutdown waits this long for a smooth stop")
    max_target_lead_m: float = Field(
        0.05, gt=0.0, le=0.5, description="a target further than this ahead of the commanded pose is pulled back"
    )
    max_target_lead_rad: float = Field(0.35, gt=0.0, le=1.5)
    max_failed_requests: int = Field(
        3, ge=1, le=100, description="this many motion requests in a row without a good reply is a fault"
    )


    def servo_params(self, halting: bool) -> tuple[float, float]:
        """(aheadtime, gain) of a ServoP/ServoJ; `halting`: it brakes to rest. Commands being tracked
        always go with `aheadtime`, so nominal motion does not depend on the halting value."""
        return (self.halt_aheadtime if halting else self.aheadtime), self.gain


class ArmDriverServiceConfig(BaseModel):
    """`bagit arm-driver`'s config file (YAML): the rig config, the driver's settings, the state rate."""

    model_config = ConfigDict(extra="forbid")

    rig_config: str | None = Field(None, description="rig config YAML: the two CR5s' addresses and bases, the safety limits")
    driver: DriverConfig = Field(default_factory=DriverConfig)
    state_rate_hz: float | None = Field(
        None, gt=0.0, le=1000.0, description="publish arm/<side>/state at most this often (None: every feedback packet)"
    )
    notice_s: float = Field(1.0, ge=0.0, le=60.0, description="an event (watchdog, clipping) shows in ArmState.error_reason this long")
