"""Checking, then opening, the configured devices, in the order that keeps the robot safe.

Called after the config and the model have been checked and before the loop starts; blocking.
``check_devices`` looks at every device without taking control of any (the sensor and servo ports exist
and may be opened; the arm's controller answers on its RTDE port), so a missing device refuses start-up
before the gripper is commanded or ur_rtde's control script replaces the user's program.
"""

from __future__ import annotations

import contextlib
import os
import socket

from slipd.config import SlipdConfig
from slipd.io.arm import URArm
from slipd.io.gripper import DynamixelGripper, DynamixelSettings
from slipd.metrics import Metrics

RTDE_PORT = 30004
ARM_PROBE_TIMEOUT_S = 2.0


class DeviceError(RuntimeError):
    """A device is missing or could not be opened at start-up; the message names the device, on one line."""


def _check_port(key: str, port: str | None, what: str) -> None:
    if port is None:
        raise DeviceError(f"{key}: not set")
    if not os.path.exists(port):
        raise DeviceError(f"{key} {port}: no such device (is the {what} plugged in?)")
    if not os.access(port, os.R_OK | os.W_OK):
        raise DeviceError(f"{key} {port}: no read/write permission (is slipd in the device's group, e.g. dialout?)")


def check_devices(cfg: SlipdConfig, sensor_port: str | None = None) -> None:
    """Every configured device is there, before any is opened: raises ``DeviceError`` naming the first
    that is not. Takes control of nothing (a TCP connect to the arm's RTDE port is closed at once)."""
    _check_port("sensor.port", sensor_port or cfg.sensor.port, "PapillArray")
    if cfg.gripper.enabled:
        _check_port("gripper.port", cfg.gripper.port, "servo bus adapter")
    if cfg.arm.enabled:
        try:
            socket.create_connection((str(cfg.arm.host), RTDE_PORT), timeout=ARM_PROBE_TIMEOUT_S).close()
        except OSError as exc:
            raise DeviceError(f"arm.host {cfg.arm.host}: RTDE port {RTDE_PORT} does not answer: {exc}") from exc


def close_quietly(*devices: object) -> None:
    """Close each device given (None: skipped), whatever the others do: a failure here must not keep the rest open."""
    for dev in devices:
        if dev is not None:
            with contextlib.suppress(Exception):
                dev.close()  # type: ignore[attr-defined]


def build_devices(cfg: SlipdConfig, metrics: Metrics) -> tuple[URArm | None, DynamixelGripper | None]:
    """Open and connect the configured arm and gripper (blocking; before the loop starts).

    Raises ``DeviceError`` naming the device; a gripper already opened is closed again when the arm fails.
    """
    gripper = arm = None
    try:
        if cfg.gripper.enabled:
            # grip_control: the object's force limit caps every command, the hold setting's included.
            limit = cfg.reaction.grip_max_force_n if cfg.reaction.policy == "grip_control" else None
            gripper = DynamixelGripper(DynamixelSettings.from_config(cfg.gripper, force_limit_n=limit), metrics=metrics)
            gripper.connect()
            # slipd owns the grip: it holds at the hold setting from the start (or keeps the tighter grip a restart
            # found) and tightens on an alarm.
            gripper.take_over()
        if cfg.arm.enabled:
            arm = URArm(cfg.arm, metrics=metrics)
            arm.connect()
    except BaseException as exc:
        # Any driver failure at start-up: refuse to run, say which device. A stop asked for meanwhile (SIGTERM, SIGINT:
        # ``slipd.daemon.service.StopRequested``) closes what is open too: the arm's control script ends, so the
        # arm cannot move on unwatched after slipd has gone.
        close_quietly(arm, gripper)
        if not isinstance(exc, Exception):
            raise
        raise DeviceError(f"device start-up failed: {' '.join(str(exc).split())}") from exc
    return arm, gripper
