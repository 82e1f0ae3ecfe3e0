"""The gripper driver (real dynamixel-sdk) against the emulated MX-28 over a real pty, both protocols.

The emulator's gripper model runs on an injected clock that only the test moves, so force and lag
checks are exact and need no sleeps; the serial traffic itself is real.
"""

from __future__ import annotations

import random
import threading
import time

import pytest
import serial
from dynamixel_sdk import COMM_SUCCESS, GroupSyncWrite, PacketHandler
from hypothesis import given, settings
from hypothesis import strategies as st

from slipd.io.gripper import DynamixelGripper, DynamixelSettings, GripperError, _TimedPortHandler, decode_hardware_error
from slipd.metrics import Metrics
from slipd.sim.devices import mx28
from slipd.sim.devices.mx28 import EmulatedMX28, JawModel, JawParams

PROTOCOLS = [2.0, 1.0]
CONTACT, K, FMAX = 2048, 0.1, 40.0  # emulator jaw defaults used below
HOLD_POS, SECURE_POS = 2150, 2400


class FakeClock:
    """Model time for the emulator: moves only when the test says so."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


def top_effort(protocol: float) -> int:
    return mx28.PWM_MAX if protocol == 2.0 else mx28.TORQUE_MAX_V1


def expected_force(position: int, effort: int, protocol: float) -> float:
    return min(K * (position - CONTACT), FMAX * effort / top_effort(protocol))


@pytest.fixture(params=PROTOCOLS, ids=["p2", "p1"])
def protocol(request) -> float:
    return request.param


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def emu(protocol, clock):
    dev = EmulatedMX28(protocol=protocol, jaw=JawParams(initial_position=2000.0), clock=clock)
    yield dev
    dev.close()


def make_settings(emu: EmulatedMX28, **over) -> DynamixelSettings:
    kw = dict(
        port=emu.port,
        protocol=emu.protocol,
        baudrate=1_000_000,
        hold_position=HOLD_POS,
        secure_position=SECURE_POS,
        hold_pwm=300,
        secure_pwm=top_effort(emu.protocol),
        open_position=1500,
        retries=2,
        packet_timeout_ms=100.0,  # generous: the test machine is shared and noisy
    )
    kw.update(over)
    return DynamixelSettings(**kw)


@pytest.fixture
def metrics() -> Metrics:
    return Metrics()


@pytest.fixture
def gripper(emu, metrics):
    g = DynamixelGripper(make_settings(emu), metrics)
    g.connect()
    yield g
    g.close()


def open_port(emu: EmulatedMX28) -> _TimedPortHandler:
    """An SDK port handler that waits in select() (the stock one spins and starves the emulator thread)."""
    port = _TimedPortHandler(emu.port, 500.0)
    assert port.openPort()
    return port


def errors(metrics: Metrics, kind: str) -> float:
    v = metrics.registry.get_sample_value("slipd_device_errors_total", {"device": "gripper", "kind": kind})
    return v or 0.0


# --------------------------------------------------------------------------------------------------
# Wire format: our emulator's framing against the vendor SDK's
# --------------------------------------------------------------------------------------------------
def test_crc_matches_the_vendor_sdk():
    sdk = PacketHandler(2.0)
    rng = random.Random(5)
    for n in (0, 1, 7, 64, 300):
        data = [rng.randrange(256) for _ in range(n)]
        assert mx28.crc16_dxl(data) == sdk.updateCRC(0, data, n)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_stuffing_round_trip_and_no_header_left(body):
    stuffed = mx28.stuff(body)
    assert mx28.unstuff(stuffed) == body
    # After stuffing, every FF FF FD is followed by the FD escape: no false header inside a packet.
    for i in range(len(stuffed) - 2):
        if stuffed[i : i + 3] == b"\xff\xff\xfd":
            assert stuffed[i + 3 : i + 4] == b"\xfd"


@settings(max_examples=100, deadline=None)
@given(st.binary(max_size=40), st.binary(max_size=10), st.integers(1, 6))
def test_parsers_find_packets_after_garbage_and_in_pieces(params, garbage, pieces):
    for encode, parse in ((mx28.encode_v2, mx28.parse_v2), (mx28.encode_v1, mx28.parse_v1)):
        wire = encode(3, mx28.INST_WRITE, params)
        stream = garbage.replace(b"\xff", b"\x00") + wire
        buf, got = bytearray(), []
        step = max(1, len(stream) // pieces)
        for i in range(0, len(stream), step):
            buf += stream[i : i + step]
            while (pkt := parse(buf)) is not None:
                got.append(pkt)
        assert [(p.dxl_id, p.instruction, p.params, p.valid) for p in got] == [(3, mx28.INST_WRITE, params, True)]


def test_corrupt_crc_gets_a_crc_error_status(emu, protocol):
    wire = bytearray((mx28.encode_v2 if protocol == 2.0 else mx28.encode_v1)(1, mx28.INST_PING))
    wire[-1] ^= 0x55
    with serial.Serial(emu.port, 1_000_000, timeout=1.0) as ser:
        ser.write(bytes(wire))
        buf = bytearray()
        parse = mx28.parse_v2 if protocol == 2.0 else mx28.parse_v1
        while (reply := parse(buf)) is None:
            chunk = ser.read(1)
            assert chunk, "no status packet for a corrupt instruction"
            buf += chunk
    # A status packet's "instruction" slot holds 0x55 (2.0) or the error byte (1.0).
    if protocol == 2.0:
        assert reply.instruction == mx28.INST_STATUS and reply.params[0] == mx28.ERR2_CRC
    else:
        assert reply.instruction == mx28.ERR1_CHECKSUM


# --------------------------------------------------------------------------------------------------
# The raw SDK against the emulator
# --------------------------------------------------------------------------------------------------
def test_sdk_ping_reports_the_mx28_model_number(emu, protocol):
    port = open_port(emu)
    try:
        model, result, error = PacketHandler(protocol).ping(port, 1)
    finally:
        port.closePort()
    assert (result, error) == (COMM_SUCCESS, 0)
    assert model == (30 if protocol == 2.0 else 29)


def test_sdk_sync_write_reaches_the_servo(emu, protocol):
    port = open_port(emu)
    addr, size = (116, 4) if protocol == 2.0 else (30, 2)
    written = threading.Event()
    emu.on_write = lambda rec: written.set()
    try:
        group = GroupSyncWrite(port, PacketHandler(protocol), addr, size)
        assert group.addParam(1, list((2222).to_bytes(size, "little")))
        assert group.addParam(9, list((1111).to_bytes(size, "little")))  # someone else on the bus
        assert group.txPacket() == COMM_SUCCESS
        assert written.wait(5.0), "sync write never reached the servo"  # a sync write has no status reply
    finally:
        port.closePort()
    assert emu.register("goal_position") == 2222
    assert emu.writes()[-1].instruction == "sync_write"


@pytest.mark.parametrize("protocol", [2.0], ids=["p2"])  # the EEPROM lock is a Protocol 2.0 rule
def test_eeprom_write_with_torque_on_is_refused(emu, gripper):
    with pytest.raises(GripperError) as info:
        gripper._write(11, bytes([1]))  # Operating Mode while torque is on
    assert info.value.kind == "status_error" and info.value.address == 11
    assert emu.register("operating_mode") == 3


# --------------------------------------------------------------------------------------------------
# The driver
# --------------------------------------------------------------------------------------------------
def test_connect_enables_torque_without_moving_the_jaw(emu, gripper, clock):
    assert gripper.model_number == (30 if emu.protocol == 2.0 else 29)
    assert emu.register("torque_enable") == 1
    clock.advance(1.0)
    assert emu.jaw_position == pytest.approx(2000.0)
    assert emu.grip_force_n == 0.0


def test_hold_sets_goal_and_effort_and_grips(emu, gripper, clock, protocol):
    gripper.hold()
    assert emu.register("goal_position") == HOLD_POS
    effort_reg = "goal_pwm" if protocol == 2.0 else "torque_limit"
    assert emu.register(effort_reg) == 300
    clock.advance(1.0)
    assert emu.grip_force_n == pytest.approx(expected_force(HOLD_POS, 300, protocol), rel=1e-3)


def test_a_restart_mid_grasp_keeps_the_tighter_grip_it_finds(emu, metrics, clock, protocol):
    """slipd restarted (systemd after a crash, a person) while the jaw holds an object it had secured: the new
    process's start-up grip (``take_over``) keeps the secure goal and effort in place, where the hold setting would
    loosen the grasp as slipd came back. A servo gripping looser than the hold setting, or with its torque off (power
    on), gets the hold setting."""
    effort_reg = "goal_pwm" if protocol == 2.0 else "torque_limit"
    first = DynamixelGripper(make_settings(emu), metrics)
    first.connect()
    assert first.take_over() == 0.0 and not first.gripping_found  # torque was off: a fresh start holds
    assert (emu.register("goal_position"), emu.register(effort_reg)) == (HOLD_POS, 300)
    first.tighten()
    clock.advance(1.0)
    secured = emu.grip_force_n
    first.close()  # the process ends; the servo keeps its torque and goal (torque_off_on_close is off)

    again = DynamixelGripper(make_settings(emu), metrics)
    again.connect()
    assert again.take_over() == 1.0 and again.level_found == 1.0 and again.gripping_found
    assert (emu.register("goal_position"), emu.register(effort_reg)) == (SECURE_POS, top_effort(protocol))
    clock.advance(1.0)
    assert emu.grip_force_n == pytest.approx(secured)  # not loosened
    mid = round(HOLD_POS + 0.2 * (SECURE_POS - HOLD_POS))
    again.release()
    again.close()

    looser = DynamixelGripper(make_settings(emu), metrics)
    looser.connect()  # found open (goal 1500, below the hold position), torque on
    assert looser.take_over() == 0.0 and not looser.gripping_found
    assert (emu.register("goal_position"), emu.register(effort_reg)) == (HOLD_POS, 300)
    looser.tighten(0.2)
    looser.close()
    partway = DynamixelGripper(make_settings(emu), metrics)
    partway.connect()
    assert partway.take_over() == pytest.approx(0.2, abs=0.01) and partway.gripping_found
    assert emu.register("goal_position") == mid
    partway.close()


def test_a_restart_keeps_a_grip_controls_low_effort_and_an_empty_jaw_gets_the_hold(protocol, clock, metrics):
    """Two restarts a helper's end-to-end probe caught: under grip control the jaw grips with the goal at the secure
    position and a low effort; the restart kept the goal but raised the effort to the hold setting (the rig's is full
    effort), squeezing the object to its force limit. And a clean exit leaves an empty jaw at the hold setting with
    torque on: the next start took that for a grip and skipped the sensor's bias."""
    effort_reg = "goal_pwm" if protocol == 2.0 else "torque_limit"
    full = top_effort(protocol)
    with EmulatedMX28(protocol=protocol, jaw=JawParams(initial_position=2000.0), clock=clock) as emu:
        g = DynamixelGripper(make_settings(emu, hold_pwm=full, secure_pwm=full), metrics)
        g.connect()
        g.take_over()
        g._command(SECURE_POS, full // 4)  # as grip_force leaves it: the goal past the object, a quarter effort
        clock.advance(1.0)
        held = emu.grip_force_n
        g.close()
        again = DynamixelGripper(make_settings(emu, hold_pwm=full, secure_pwm=full), metrics)
        again.connect()
        again.take_over()
        assert again.gripping_found and emu.register(effort_reg) == full // 4
        clock.advance(1.0)
        assert emu.grip_force_n == pytest.approx(held)  # not squeezed
        again.close()
    with EmulatedMX28(protocol=protocol, jaw=JawParams(initial_position=2000.0, contact_position=None),
                      clock=clock) as emu:
        g = DynamixelGripper(make_settings(emu), metrics)
        g.connect()
        g.take_over()
        clock.advance(1.0)
        g.close()  # a clean exit: torque on, the goal at the hold position, nothing in the jaw
        again = DynamixelGripper(make_settings(emu, hold_pwm=250), metrics)
        again.connect()
        assert again.take_over() == 0.0 and not again.gripping_found
        assert emu.register(effort_reg) == 250  # the hold setting as configured now
        again.close()


def test_hold_force_is_capped_by_the_effort_setting(emu, metrics, clock, protocol):
    g = DynamixelGripper(make_settings(emu, hold_pwm=150), metrics)
    g.connect()
    try:
        g.hold()
        clock.advance(1.0)
        capped = FMAX * 150 / top_effort(protocol)
        assert capped < K * (HOLD_POS - CONTACT)  # the cap is what binds here
        assert emu.grip_force_n == pytest.approx(capped, rel=1e-3)
    finally:
        g.close()


def test_tighten_reaches_the_servo_and_force_follows_with_lag(emu, gripper, clock, protocol):
    gripper.hold()
    clock.advance(1.0)
    f_hold = emu.grip_force_n
    emu.clear_writes()

    t_sent = gripper.tighten()

    recs = emu.writes()
    values = {k: v for r in recs for k, v in r.values.items()}
    assert values["goal_position"] == SECURE_POS
    assert values["goal_pwm" if protocol == 2.0 else "torque_limit"] == top_effort(protocol)
    assert gripper.last_tighten_monotonic == t_sent
    assert t_sent <= recs[0].t  # stamped when the bytes left, before the servo parsed them
    # Model time has not moved: the command waits for the servo's next refresh tick.
    assert emu.grip_force_n == pytest.approx(f_hold)
    clock.advance(0.025)
    f_early = emu.grip_force_n
    f_secure = expected_force(SECURE_POS, top_effort(protocol), protocol)
    assert f_hold < f_early < 0.9 * f_secure  # rising, but lagging
    clock.advance(1.0)
    assert emu.grip_force_n == pytest.approx(f_secure, rel=1e-3)


def test_tighten_level_interpolates_between_hold_and_secure(emu, gripper, protocol):
    gripper.hold()
    gripper.tighten(0.5)
    top = top_effort(protocol)
    assert emu.register("goal_position") == round((HOLD_POS + SECURE_POS) / 2)
    assert emu.register("goal_pwm" if protocol == 2.0 else "torque_limit") == round((300 + top) / 2)
    gripper.tighten(7.0)  # clipped to secure
    assert emu.register("goal_position") == SECURE_POS
    with pytest.raises(ValueError, match="finite"):
        gripper.tighten(float("nan"))


def test_read_status_reports_load_and_position(emu, gripper, clock):
    gripper.tighten()
    clock.advance(1.0)
    s = gripper.read_status()
    f = emu.grip_force_n
    assert s.position == SECURE_POS and s.goal_position == SECURE_POS
    assert s.load == pytest.approx(100.0 * f / FMAX, abs=0.11)
    assert s.load > 0  # towards closing
    assert s.torque_enabled and not s.moving and s.healthy
    assert s.hardware_error == 0 and s.hardware_errors == ()


def test_release_opens_the_jaw(emu, gripper, clock):
    gripper.hold()
    clock.advance(1.0)
    gripper.release()
    clock.advance(1.0)
    assert emu.jaw_position == pytest.approx(1500.0, abs=0.5)
    assert emu.grip_force_n == pytest.approx(0.0, abs=1e-6)


def test_absent_id_retries_then_raises(emu, metrics):
    g = DynamixelGripper(make_settings(emu, dxl_id=7, retries=2), metrics)
    with pytest.raises(GripperError) as info:
        g.connect()
    g.close()
    err = info.value
    assert err.kind == "rx_timeout" and "3 attempt" in str(err) and "id 7" in str(err)
    assert errors(metrics, "rx_timeout") == 3  # one per attempt, bounded


def test_unplugged_servo_then_back(emu, metrics):
    g = DynamixelGripper(make_settings(emu, retries=1), metrics)
    emu.absent = True
    with pytest.raises(GripperError, match="no status packet"):
        g.connect()
    emu.absent = False
    g.connect()
    g.hold()
    assert emu.register("goal_position") == HOLD_POS
    g.close()


def test_a_short_silence_is_bridged_by_retries(emu, metrics):
    g = DynamixelGripper(make_settings(emu, retries=15), metrics)
    g.connect()
    try:
        emu.mute_for(0.15)
        g.tighten()  # ~20 ms per attempt: outlasts the silence
        assert emu.register("goal_position") == SECURE_POS
        assert errors(metrics, "rx_timeout") >= 1
    finally:
        g.close()


def test_a_late_answer_to_an_earlier_request_is_dropped_and_the_read_asked_again(emu, gripper, metrics):
    """A status packet that arrives after its request gave up is read as the next request's answer; a read of
    another size must not fail the gripper (and with it the arm) for it."""
    send = emu._send
    stale = [emu._status(0, b"\x00\x00")]  # a two-byte read's answer, complete and valid, but late

    def late_then_real(reply: bytes) -> None:
        send((stale.pop() if stale else b"") + reply)

    emu._send = late_then_real  # type: ignore[method-assign]
    status = gripper.read_status()
    assert status.healthy and not stale
    assert errors(metrics, "rx_corrupt") == 1


def test_overload_is_reported_and_recovered(emu, gripper, clock, metrics, protocol):
    gripper.hold()
    clock.advance(1.0)
    emu.inject_overload()
    clock.advance(0.5)
    s = gripper.read_status()
    assert s.hardware_errors == ("overload",) and not s.healthy
    assert emu.grip_force_n == pytest.approx(0.0, abs=1e-3)  # the shutdown dropped the torque
    if protocol == 2.0:
        assert not s.torque_enabled
        with pytest.raises(GripperError) as info:
            gripper.tighten()
        assert info.value.kind == "hardware_error" and "overload" in str(info.value)
        assert errors(metrics, "hardware_error") == 1
        gripper.recover()  # reboot, position mode, torque on, hold
    else:
        # 1.0 shutdown zeroes Torque Limit; the tighten packet rewrites it and so re-arms the servo.
        gripper.tighten()
    clock.advance(1.0)
    s = gripper.read_status()
    assert s.healthy and s.hardware_error == 0
    assert emu.grip_force_n > 5.0


def test_sustained_saturation_trips_overload_in_the_model(protocol, clock, metrics):
    jaw = JawParams(initial_position=2000.0, overload_after_s=0.5)
    with EmulatedMX28(protocol=protocol, jaw=jaw, clock=clock) as dev:
        g = DynamixelGripper(make_settings(dev, hold_pwm=100), metrics)
        g.connect()
        try:
            g.hold()  # the position asks for more force than 100/885 PWM allows: saturated
            clock.advance(0.3)
            assert g.read_status().hardware_error == 0
            clock.advance(0.5)
            assert g.read_status().hardware_errors == ("overload",)
        finally:
            g.close()


def test_torque_off_servo_ignores_goals(emu, gripper, clock, protocol):
    gripper.hold()
    clock.advance(1.0)
    # Someone switched torque off (e.g. a power blip under 1.0, or a technician): goals are stored, not obeyed.
    gripper.close()
    emu_port = open_port(emu)
    try:
        res, err = PacketHandler(protocol).write1ByteTxRx(emu_port, 1, 64 if protocol == 2.0 else 24, 0)
        assert (res, err) == (COMM_SUCCESS, 0)
    finally:
        emu_port.closePort()
    clock.advance(1.0)
    assert emu.grip_force_n == pytest.approx(0.0, abs=1e-6)
    g = DynamixelGripper(make_settings(emu))
    g._open()  # talk without connect(), which would switch torque back on
    try:
        # The goal is sent (the reaction's latency is the same), then the torque check makes it a failure: a tighten
        # that grips nothing must stay owed, not pass for done.
        with pytest.raises(GripperError) as info:
            g.tighten()
        assert info.value.kind == "torque_off"
        clock.advance(1.0)
        assert emu.register("goal_position") == SECURE_POS
        assert emu.grip_force_n == pytest.approx(0.0, abs=1e-6)
        assert emu.jaw_position == pytest.approx(CONTACT, abs=0.5)
        assert not g.read_status().torque_enabled
        with pytest.raises(GripperError, match="torque is off"):
            g.hold()  # refused while the servo's torque is known off: nothing sent
        assert emu.register("goal_position") == SECURE_POS
        g.connect()  # a person's restart: torque on again, commands obeyed
        g.hold()
        clock.advance(1.0)
        assert emu.register("goal_position") == HOLD_POS and emu.grip_force_n > 1.0
    finally:
        g.close()


@pytest.mark.parametrize("protocol", [2.0], ids=["p2"])  # the emulator's power cycle follows the 2.0 table
def test_a_power_blip_makes_the_next_tighten_fail_and_stay_failed(emu, gripper, clock):
    """The servo's supply dips (the USB adapter stays up): it comes back with torque off and no error. A tighten
    sent then used to return as done while the jaw applied 0 N."""
    gripper.hold()
    clock.advance(1.0)
    emu.reboot()
    time.sleep(emu.boot_s + 0.05)
    with pytest.raises(GripperError) as info:
        gripper.tighten()
    assert info.value.kind == "torque_off"
    clock.advance(1.0)
    assert emu.grip_force_n == pytest.approx(0.0, abs=1e-6) and emu.register("torque_enable") == 0
    with pytest.raises(GripperError):
        gripper.tighten(0.5)  # known off: refused before sending
    assert not gripper.read_status().healthy
    pwm = emu.register("goal_pwm")
    with pytest.raises(GripperError) as info:
        gripper.grip_force(1.0)  # grip_control's command too (it has no read after it: 60 a second)
    assert info.value.kind == "torque_off" and emu.register("goal_pwm") == pwm  # nothing sent


def test_an_unplugged_adapter_drops_the_port_and_reconnect_reopens_it_without_torque(protocol, clock, metrics,
                                                                                      tmp_path):
    """The USB adapter is unplugged and plugged back under the same (udev) path: the I/O error drops the dead port,
    ``reconnect`` opens the path anew and pings; it switches nothing on (a servo that lost power stays off)."""
    link = tmp_path / "ttyDXL"

    def plug() -> EmulatedMX28:
        dev = EmulatedMX28(protocol=protocol, jaw=JawParams(initial_position=2000.0), clock=clock)
        if link.is_symlink():
            link.unlink()
        link.symlink_to(dev.port)
        return dev

    first = plug()
    g = DynamixelGripper(make_settings(first, port=str(link)), metrics)
    second = None
    try:
        g.connect()
        g.hold()
        first.close()  # unplugged
        with pytest.raises(GripperError) as info:
            g.read_status()
        assert info.value.kind == "io" and errors(metrics, "io") >= 1  # was a bare termios.error, uncounted
        assert not g.reconnect()  # nothing there yet
        second = plug()  # back, the same path; a new servo power-up: torque off
        assert g.reconnect()
        assert second.register("torque_enable") == 0  # reconnect switched nothing on
        st = g.read_status()
        assert not st.torque_enabled and not st.healthy
        with pytest.raises(GripperError, match="torque is off"):
            g.tighten()
    finally:
        g.close()
        if second is not None:
            second.close()


@pytest.mark.parametrize("protocol", [2.0], ids=["p2"])  # REBOOT is a Protocol 2.0 instruction
def test_emulator_reboot_resets_ram(emu, gripper, clock):
    gripper.tighten()
    clock.advance(1.0)
    result, _ = PacketHandler(2.0).reboot(gripper._port, 1)
    assert result == COMM_SUCCESS
    assert emu.register("torque_enable") == 0
    assert emu.register("goal_pwm") == mx28.PWM_MAX


def test_gripper_calls_run_on_a_device_worker(emu, gripper):
    from slipd.daemon.worker import DeviceWorker

    w = DeviceWorker("gripper")
    try:
        t_sent = w.submit(gripper.tighten, 1.0).result(timeout=5)
        status = w.submit(gripper.read_status).result(timeout=5)
    finally:
        w.close()
    assert t_sent == gripper.last_tighten_monotonic
    assert status.goal_position == SECURE_POS


def test_commands_before_connect_fail_clearly(emu):
    g = DynamixelGripper(make_settings(emu))
    with pytest.raises(GripperError, match="not connected"):
        g.hold()


def test_missing_port_fails_clearly(tmp_path):
    s = DynamixelSettings(port=str(tmp_path / "ttyNONE"), hold_position=100, secure_position=200, hold_pwm=1,
                          secure_pwm=2)
    with pytest.raises(GripperError, match="cannot open the serial port") as info:
        DynamixelGripper(s).connect()
    assert info.value.kind == "open_failed"


# --------------------------------------------------------------------------------------------------
# Settings, helpers, the model on its own
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("over", "key"),
    [
        ({"protocol": 3.0}, "protocol"),
        ({"dxl_id": 253}, "dxl_id"),
        ({"baudrate": 12345}, "baudrate"),
        ({"secure_pwm": 900}, "secure_pwm"),
        ({"secure_pwm": 100}, "secure_pwm"),
        ({"secure_position": 2150}, "secure_position"),
        ({"open_position": 2300}, "open_position"),
        ({"hold_position": 5000}, "hold_position"),
        ({"retries": -1}, "retries"),
    ],
)
def test_settings_reject_bad_values_naming_the_key(over, key):
    kw = dict(port="/dev/null", hold_position=2150, secure_position=2400, hold_pwm=300, secure_pwm=885,
              open_position=1500)
    kw.update(over)
    with pytest.raises(ValueError, match=rf"DynamixelSettings\.{key}"):
        DynamixelSettings(**kw)


def test_protocol1_effort_range_is_the_torque_limit():
    s = DynamixelSettings(port="/dev/null", protocol=1.0, hold_position=2150, secure_position=2400, hold_pwm=300,
                          secure_pwm=1023)
    assert s.secure_pwm == 1023


def test_closing_towards_lower_ticks_is_supported():
    s = DynamixelSettings(port="/dev/null", hold_position=2000, secure_position=1800, hold_pwm=300, secure_pwm=885,
                          open_position=2500)
    assert s.closing_sign == -1


def test_decode_hardware_error():
    assert decode_hardware_error(0) == ()
    assert decode_hardware_error(0x24) == ("overheating", "overload")
    assert decode_hardware_error(0x40) == ("unknown_0x40",)


def test_jaw_model_applies_commands_on_refresh_ticks():
    m = JawModel(JawParams(refresh_hz=62.0), t0=0.0)
    t_apply = m.command(0.001, torque_on=True, goal=2300.0)
    assert t_apply == pytest.approx(1 / 62)
    m.advance(0.015)
    assert not m.torque_on
    m.advance(0.017)
    assert m.torque_on and m.goal == 2300.0


def test_jaw_model_with_nothing_in_the_jaw_never_grips():
    m = JawModel(JawParams(contact_position=None, refresh_hz=None), t0=0.0)
    m.command(0.0, torque_on=True, goal=3000.0, effort=1.0)
    m.advance(2.0)
    assert m.force == 0.0 and m.position == pytest.approx(3000.0, abs=0.5)


def test_an_object_force_limit_caps_every_command_the_hold_included(emu, metrics, clock, protocol):
    """grip_control's object limit (``force_limit_n``) binds the start-up hold, a tighten and a force command: the
    hold setting alone (position past the object, effort 300 = 13.6 N here) would squeeze a 5 N object with 10 N."""
    top = top_effort(protocol)
    cap = int(5.0 / FMAX * top)  # rounded down: never above the limit
    g = DynamixelGripper(make_settings(emu, force_limit_n=5.0), metrics)
    g.connect()
    effort_reg = "goal_pwm" if protocol == 2.0 else "torque_limit"
    try:
        g.hold()
        clock.advance(1.0)
        assert emu.register(effort_reg) == cap
        assert K * (HOLD_POS - CONTACT) > 5.0  # the position alone would ask for more
        assert emu.grip_force_n <= 5.0 and emu.grip_force_n == pytest.approx(FMAX * cap / top, rel=1e-3)
        g.tighten()
        clock.advance(1.0)
        assert emu.register(effort_reg) == cap and emu.grip_force_n <= 5.0
        g.grip_force(30.0)
        clock.advance(1.0)
        assert emu.register(effort_reg) == cap and emu.grip_force_n <= 5.0
        g.grip_force(2.0)  # below the limit: as asked
        clock.advance(1.0)
        assert emu.grip_force_n == pytest.approx(2.0, abs=FMAX / top)
    finally:
        g.close()
    with pytest.raises(ValueError, match="force_limit_n"):
        make_settings(emu, force_limit_n=50.0)  # above the jaw's full force: a limit that never binds


@pytest.mark.parametrize(("protocol", "register", "value", "key"), [
    (2.0, "pwm_limit", 200, "hold_pwm"),
    (2.0, "max_position_limit", 2300, "secure_position"),
    (2.0, "min_position_limit", 1600, "open_position"),
    (1.0, "ccw_angle_limit", 2300, "secure_position"),
    (1.0, "cw_angle_limit", 0, "wheel mode"),
], ids=["p2-pwm", "p2-max-position", "p2-min-position", "p1-angle", "p1-wheel"])
def test_connect_refuses_settings_beyond_the_servos_own_limits(emu, metrics, register, value, key):
    """A limit set on the servo (EEPROM) narrower than the config: start-up passed and the servo refused the first
    command beyond it, the tighten of a slip alarm (with Goal PWM already raised, under 2.0). Now connect refuses,
    naming the key, before anything is written."""
    emu.table.set(register, value)
    if key == "wheel mode":
        emu.table.set("ccw_angle_limit", 0)
    g = DynamixelGripper(make_settings(emu, hold_pwm=300), metrics)
    try:
        with pytest.raises(GripperError) as info:
            g.connect()
        assert info.value.kind == "limits" and key in str(info.value)
        assert emu.register("torque_enable") == 0  # nothing switched on, nothing moved
    finally:
        g.close()


@pytest.mark.parametrize("protocol", [2.0], ids=["p2"])
def test_grip_force_stays_within_the_servos_pwm_limit(emu, metrics, caplog):
    """grip_control's force commands reach up to the effort cap: past a lower PWM Limit the servo refused them (a grip
    command failure, a fail-safe) just when the controller wanted the most grip. They stop at the limit, and start-up
    says what grip that leaves."""
    emu.table.set("pwm_limit", 600)
    g = DynamixelGripper(make_settings(emu, hold_pwm=300, secure_pwm=600), metrics)
    try:
        with caplog.at_level("WARNING"):
            g.connect()
        assert "PWM Limit 600 caps the grip" in caplog.text
        g.grip_force(g.settings.max_force_n)
        assert emu.register("goal_pwm") == 600
    finally:
        g.close()


def test_the_emulators_write_log_is_bounded(emu, gripper):
    """A soak of hours runs the emulated servo in the daemon's process: its log of writes must not grow with it."""
    for _ in range(mx28.MAX_WRITES // 2 + 10):
        gripper.hold()
        gripper.tighten()
    writes = emu.writes()
    assert len(writes) == mx28.MAX_WRITES
    assert writes[-1].values.get("goal_position") == SECURE_POS
