"""Opening the configured devices, in the order that keeps the robot safe.

Called after the config and the model have been checked and before the loop starts; blocking.
"""

from __future__ import annotations

from slipd.config import SlipdConfig
from slipd.io.arm import URArm
from slipd.io.gripper import DynamixelGripper
from slipd.metrics import Metrics


class DeviceError(RuntimeError):
    """A device could not be opened at start-up; the message names the device."""


def build_devices(cfg: SlipdConfig, metrics: Metrics) -> tuple[URArm | None, DynamixelGripper | None]:
    """Open and connect the configured arm and gripper (blocking; before the loop starts).

    Raises ``DeviceError`` naming the device; a gripper already opened is closed again when the arm fails.
    """
    try:
        return _build(cfg, metrics)
    except DeviceError:
        raise
    except Exception as exc:  # any driver failure at start-up: refuse to run, say which device
        raise DeviceError(f"device start-up failed: {exc}") from exc


def _build(cfg: SlipdConfig, metrics: Metrics) -> tuple[URArm | None, DynamixelGripper | None]:
    arm = gripper = None
    if cfg.gripper.enabled:
        from slipd.io.gripper import DynamixelSettings

        g = cfg.gripper
        gripper = DynamixelGripper(
            DynamixelSettings(
                port=g.port, baudrate=g.baudrate, dxl_id=g.id, protocol=float(g.protocol),
                hold_position=g.hold_position, secure_position=g.secure_position,
                hold_pwm=g.hold_effort, secure_pwm=g.secure_effort,
                retries=g.retries, packet_timeout_ms=g.packet_timeout_ms,
            ),
            metrics=metrics,
        )
        gripper.connect()
        # slipd owns the grip: it holds at the hold setting from the start and tightens on an alarm.
        gripper.hold()
    if cfg.arm.enabled:
        from slipd.io.arm import URSettings

        a = cfg.arm
        arm = URArm(
            URSettings(host=a.host, frequency=a.rtde_frequency, stop_deceleration=a.stop_deceleration,
                       stop_method=a.stop_method),
            metrics=metrics,
        )
        arm.connect()
    return arm, gripper
