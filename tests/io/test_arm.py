"""The UR arm driver against the real ur_rtde client and our emulated controller in its own process.

ur_rtde interfaces take about a second to tear down, so one controller and one URArm are shared by
the module's integration tests (they run in file order and leave the arm running and connected).
"""

from __future__ import annotations

import math
import random
import struct
import time

import pytest

from slipd.config.schema import ArmConfig
from slipd.io.arm import ArmError, ArmState, URArm, URSettings
from slipd.metrics import Metrics
from slipd.sim.devices import rtde_protocol as rp
from slipd.sim.devices.ur_controller import URControllerConfig, URControllerProcess
from slipd.sim.devices.ur_motion import LinearMotion

pytest.importorskip("rtde_control")
pytest.importorskip("rtde_receive")

LIFT = (0.30, -0.20, 0.80, 0.0, 3.1416, 0.0)  # 0.4 m above the initial pose


def _start_controller(**kw: object) -> URControllerProcess:
    """A controller on a random 127.0.0.x (parallel test runs must not collide on the fixed UR ports)."""
    last: Exception | None = None
    for _ in range(6):
        host = f"127.0.0.{random.randint(2, 254)}"
        try:
            return URControllerProcess(host, **kw).start()
        except RuntimeError as e:  # address in use by another run: pick another
            last = e
    raise RuntimeError(f"could not start an emulated controller: {last}")


def _count(metrics: Metrics, kind: str) -> float:
    return metrics.registry.get_sample_value("slipd_device_errors_total", {"device": "arm", "kind": kind}) or 0.0


def _wait(cond, timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


# ---------------------------------------------------------------------------------------------------------------
# Pure units: protocol framing and the motion model
# ---------------------------------------------------------------------------------------------------------------
def test_recipe_types_and_round_trip() -> None:
    r = rp.make_recipe(3, ["input_int_register_0", "input_double_register_5", "actual_TCP_pose", "robot_status_bits"])
    assert r.types == ("INT32", "DOUBLE", "VECTOR6D", "UINT32") and r.valid
    packet = r.pack([7, 1.5, (1, 2, 3, 4, 5, 6), 3])
    (ptype, payload), = list(rp.PacketReader().feed(packet))
    assert ptype == rp.DATA_PACKAGE and payload[0] == 3
    assert r.unpack(payload[1:]) == {"input_int_register_0": 7, "input_double_register_5": 1.5,
                                     "actual_TCP_pose": (1, 2, 3, 4, 5, 6), "robot_status_bits": 3}
    assert not rp.make_recipe(1, ["actual_TCP_pose", "no_such_variable"]).valid
    assert rp.variable_type("output_int_register_48") == rp.NOT_FOUND


def test_packet_reader_reassembles_split_packets_and_rejects_bad_size() -> None:
    a, b = rp.encode(rp.CONTROL_PACKAGE_START), rp.encode(rp.GET_URCONTROL_VERSION, struct.pack(">I", 5))
    reader = rp.PacketReader()
    stream = a + b
    got = []
    for i in range(len(stream)):  # one byte at a time
        got += list(reader.feed(stream[i : i + 1]))
    assert got == [(rp.CONTROL_PACKAGE_START, b""), (rp.GET_URCONTROL_VERSION, struct.pack(">I", 5))]
    with pytest.raises(ValueError, match="smaller than its header"):
        list(rp.PacketReader().feed(b"\x00\x01U"))


def test_linear_motion_trapezoid_reaches_target_and_stop_decelerates() -> None:
    m = LinearMotion((0, 0, 0, 0, 0, 0))
    m.move_to((0.1, 0, 0, 0, 0, 0), speed=0.25, accel=1.0)
    peak, steps = 0.0, 0
    while m.active and steps < 10_000:
        m.step(0.002)
        peak, steps = max(peak, m.speed), steps + 1
    assert m.pose[0] == pytest.approx(0.1, abs=1e-6) and m.velocity == [0.0] * 6
    assert peak <= 0.25 + 1e-9
    # 0.1 m with a = 1: accelerate to ~0.25 m/s, cruise, brake; at least the triangle time 2*sqrt(d/a).
    assert steps * 0.002 >= 2 * math.sqrt(0.1 / 1.0) * 0.99

    m.move_to((0.1, 0, 1.0, 0, 0, 0), speed=0.5, accel=5.0)
    for _ in range(100):
        m.step(0.002)
    v0 = m.speed
    assert v0 == pytest.approx(0.5)
    m.stop(2.0)
    n = 0
    while m.active:
        m.step(0.002)
        n += 1
    assert n * 0.002 == pytest.approx(v0 / 2.0, abs=0.004)  # v/a seconds of deceleration
    assert m.pose[2] < 1.0  # halted before the target
    with pytest.raises(ValueError, match="finite"):
        m.move_to((0, 0, math.nan, 0, 0, 0), 0.1, 1.0)


def test_settings_validation_names_the_field() -> None:
    with pytest.raises(ValueError, match="stop_method"):
        URSettings(host="127.0.0.2", stop_method="brake")
    with pytest.raises(ValueError, match="use_control"):
        URSettings(host="127.0.0.2", stop_method="stopl", use_control=False)
    with pytest.raises(ValueError, match="stop_deceleration"):
        URSettings(host="127.0.0.2", stop_deceleration=0)
    with pytest.raises(ValueError, match="loopback"):
        URControllerConfig(host="10.0.0.2")


# ---------------------------------------------------------------------------------------------------------------
# Real ur_rtde against the emulated controller
# ---------------------------------------------------------------------------------------------------------------
def test_connect_to_absent_controller_raises_arm_error_and_counts() -> None:
    ctl = _start_controller()
    host = ctl.host
    ctl.stop()  # nothing listens there any more: connection refused
    m = Metrics()
    with pytest.raises(ArmError, match=f"UR arm at {host}: cannot connect"):
        URArm(URSettings(host=host), m).connect()
    assert _count(m, "connect") == 1


@pytest.fixture(scope="module")
def controller():
    ctl = _start_controller()
    yield ctl
    ctl.stop()


@pytest.fixture(scope="module")
def metrics() -> Metrics:
    return Metrics()


@pytest.fixture(scope="module")
def arm(controller: URControllerProcess, metrics: Metrics):
    # A reconnect arms the watchdog on the script it uploads; these tests do not kick: a period longer than the module.
    settings = URSettings(host=controller.host, stop_method="stopl", stop_deceleration=3.0,
                          fallback_to_dashboard=False, watchdog_s=600.0)
    a = URArm(settings, metrics)
    a.connect()
    yield a
    a.close()


def _lift_and_wait_moving(controller: URControllerProcess, speed: float = 0.25) -> None:
    controller.wait_for(lambda s: not s.moving, what="arm at rest before the lift")
    controller.move_l(LIFT, speed=speed, accel=1.2)
    controller.wait_for(lambda s: s.linear_speed > 0.1, what="lift under way")


def _back_to_start(controller: URControllerProcess) -> None:
    controller.wait_for(lambda s: not s.moving, what="arm at rest")
    controller.set_pose(URControllerConfig().initial_pose)


def test_receive_reads_served_pose_and_control_script_runs(controller: URControllerProcess, arm: URArm) -> None:
    assert arm.is_connected()
    st = arm.read_state()
    assert isinstance(st, ArmState) and st.connected
    assert st.pose == pytest.approx(URControllerConfig().initial_pose)
    assert st.speed == pytest.approx((0.0,) * 6)
    assert st.program_running and not st.protective_stop and st.safety_mode == 1 and st.robot_mode == 7
    state = controller.state()
    assert state.control_script_running and state.program_running and state.scripts_received >= 1
    assert arm._control.isProgramRunning()


def test_stopl_halts_a_user_move_in_progress(controller: URControllerProcess, arm: URArm) -> None:
    _lift_and_wait_moving(controller)
    before = controller.state()
    assert arm.read_state().linear_speed > 0.05  # the receive interface sees the move too

    result = arm.stop("test slip")
    assert result.ok and result.method == "stopl" and result.reason == "test slip" and not result.protective_stop
    assert result.t_issued <= result.t_returned and arm.last_stop is result

    after = controller.wait_for(lambda s: not s.moving, timeout=2.0, what="arm halted")
    assert after.stop_count == before.stop_count + 1
    assert after.last_stop_kind == "stopl" and after.last_stop_decel == pytest.approx(3.0)
    # The stop was received after we issued it and before ur_rtde's call returned.
    assert result.t_issued <= after.last_stop_received_t <= result.t_returned
    assert after.tcp_speed == pytest.approx((0.0,) * 6)
    assert after.tcp_pose[2] < LIFT[2] - 0.05  # halted well short of the lift target
    _wait(lambda: arm.read_state().linear_speed == 0.0, what="served speed zero")
    _back_to_start(controller)


def test_control_movel_async_and_speedstop_reach_the_emulator(controller: URControllerProcess, arm: URArm) -> None:
    c = arm._control
    moves = controller.state().moves_started
    assert c.moveL(list(LIFT), 0.2, 1.0, True)
    controller.wait_for(lambda s: s.moves_started == moves + 1 and s.linear_speed > 0.05, what="rtde moveL")
    assert c.getAsyncOperationProgress() >= 0  # async progress word says "running"
    stops = controller.state().stop_count
    assert c.speedStop(2.0)
    s = controller.wait_for(lambda s: not s.moving, timeout=2.0, what="speedStop halt")
    assert s.stop_count == stops + 1 and s.last_stop_kind == "speed_stop"
    _wait(lambda: c.getAsyncOperationProgress() < 0, what="async move reported finished")
    _back_to_start(controller)


def test_protective_stop_detected_and_commands_fail(controller: URControllerProcess, arm: URArm,
                                                    metrics: Metrics) -> None:
    before = _count(metrics, "protective_stop")
    failed_before = _count(metrics, "stop_failed")
    _lift_and_wait_moving(controller)
    controller.inject_protective_stop()
    controller.wait_for(lambda s: not s.moving, what="protective stop halts the arm")
    _wait(lambda: arm.read_state().protective_stop, what="protective stop seen over RTDE")
    st = arm.read_state()
    assert st.protective_stop and not st.program_running and st.safety_mode == 3
    assert _count(metrics, "protective_stop") == before + 1  # once per occurrence, not per read

    result = arm.stop("during protective stop")
    assert not result.ok and result.protective_stop and "not running" in result.error
    assert _count(metrics, "stop_failed") == failed_before + 1

    assert arm.unlock_protective_stop()  # dashboard unlock + play resumes the paused control script
    _wait(lambda: arm.read_state().program_running and not arm.read_state().protective_stop, what="resumed")
    _back_to_start(controller)
    _lift_and_wait_moving(controller)
    assert arm.stop("after unlock").ok
    controller.wait_for(lambda s: not s.moving, timeout=2.0, what="halt after unlock")
    _back_to_start(controller)


def test_disconnect_detected_and_reconnect_works(controller: URControllerProcess, arm: URArm,
                                                 metrics: Metrics) -> None:
    before = _count(metrics, "disconnected")
    controller.drop_connections(down_s=2.0)  # long enough that a loaded machine still reads it down
    _wait(lambda: not arm.is_connected(), timeout=3.0, what="disconnect noticed")
    st = arm.read_state()
    assert not st.connected and all(math.isnan(x) for x in st.pose)
    for _ in range(5):
        arm.read_state()
    assert _count(metrics, "disconnected") == before + 1  # one loss of the link, however many reads
    time.sleep(2.1)  # the controller accepts connections again
    assert arm.reconnect()
    assert arm.is_connected()
    _wait(lambda: arm.read_state().program_running, what="control script back after reconnect")
    assert arm.read_state().pose == pytest.approx(URControllerConfig().initial_pose)
    _lift_and_wait_moving(controller)
    assert arm.stop("after reconnect").ok
    controller.wait_for(lambda s: not s.moving, timeout=2.0, what="halt after reconnect")
    _back_to_start(controller)


def test_refused_stop_falls_back_to_dashboard_and_reconnect_reuploads(controller: URControllerProcess, arm: URArm,
                                                                      metrics: Metrics) -> None:
    fallback = URArm(URSettings(host=controller.host, fallback_to_dashboard=True), metrics)
    # Share the module's ur_rtde interfaces (a second control interface would replace the script).
    fallback._receive, fallback._control = arm._receive, arm._control
    _lift_and_wait_moving(controller)
    controller.refuse_next_command()
    result = fallback.stop("refused")
    assert result.ok and result.method == "stopl->dashboard_stop" and "stopL" in result.error
    s = controller.wait_for(lambda s: not s.moving, timeout=3.0, what="dashboard stop halts")
    assert s.last_stop_kind == "dashboard_stop" and not s.control_script_running
    assert arm.reconnect()  # re-uploads ur_rtde's control script
    assert arm.read_state().program_running and controller.state().control_script_running
    fallback._dashboard.disconnect()
    _back_to_start(controller)


@pytest.mark.parametrize("from_config", [False, True])
def test_dashboard_pause_stops_the_user_program_without_the_control_script(from_config: bool) -> None:
    """Also as the daemon builds it from its config (``arm.stop_method: dashboard_pause``): it once created the
    control interface anyway, which uploads ur_rtde's script over the user's program."""
    with _start_controller() as ctl:
        if from_config:
            cfg = ArmConfig(host=ctl.host, stop_method="dashboard_pause")
            arm = URArm(URSettings.from_config(cfg))
        else:
            arm = URArm(URSettings(host=ctl.host, stop_method="dashboard_pause", use_control=False))
        arm.connect()
        try:
            assert arm._control is None and not ctl.state().control_script_running
            _lift_and_wait_moving(ctl)
            assert arm.read_state().program_running  # the user's program, not ur_rtde's
            result = arm.stop("pause")
            assert result.ok and result.method == "dashboard_pause"
            s = ctl.wait_for(lambda s: not s.moving, timeout=3.0, what="pause halts")
            assert s.last_stop_kind == "dashboard_pause" and s.runtime_state == 4  # PAUSED
            assert s.scripts_received == 0  # nothing was uploaded: the user's program stayed in place
            # Nothing left to pause: the controller refuses and the result says so.
            again = arm.stop("pause again")
            assert not again.ok and "Failed to execute" in again.error
        finally:
            arm.close()


def test_asynchronous_stopl_returns_before_standstill(controller: URControllerProcess, arm: URArm) -> None:
    slow = URArm(URSettings(host=controller.host, stop_deceleration=0.2, stop_asynchronous=True,
                            fallback_to_dashboard=False))
    slow._receive, slow._control = arm._receive, arm._control  # share the module's ur_rtde interfaces
    _lift_and_wait_moving(controller)
    result = slow.stop("async")
    # At 0.2 m/s^2 the arm needs >= 0.5 s to halt; a synchronous stopL would only return at standstill.
    assert result.ok and controller.state().moving
    s = controller.wait_for(lambda s: not s.moving, timeout=5.0, what="async stop completes")
    assert s.last_stop_kind == "stopl" and s.last_stop_decel == pytest.approx(0.2)
    _wait(lambda: arm._control.getAsyncOperationProgress() < 0, what="async stop reported finished")
    _back_to_start(controller)


def test_upper_range_registers_and_watchdog() -> None:
    import rtde_control

    with _start_controller() as ctl:
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT | \
            rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        c = rtde_control.RTDEControlInterface(ctl.host, -1.0, flags)
        try:
            target = (0.30, -0.20, 0.45, 0.0, 3.1416, 0.0)
            assert c.moveL(list(target), 0.2, 1.0, False)  # synchronous: returns at the target
            assert ctl.state().tcp_pose == pytest.approx(target)
            # A watchdog nobody kicks stops the control script (rtde_set_watchdog(..., "stop")).
            assert c.setWatchdog(50.0)
            s = ctl.wait_for(lambda s: not s.control_script_running, timeout=3.0, what="watchdog expiry")
            assert s.last_stop_kind == "watchdog"
        finally:
            c.disconnect()


def test_a_script_uploaded_by_a_reconnect_is_watched_at_once(metrics: Metrics) -> None:
    """ur_rtde's reconnect uploads a fresh control script without a watchdog. The daemon reconnects while blind too
    (it does not kick then): the script it leaves running must end by itself, or the cell could move the arm unwatched
    (the watchdog was armed lazily at the next kick, which a blind daemon never sends)."""
    with _start_controller() as ctl:
        a = URArm(URSettings(host=ctl.host, stop_method="stopl", fallback_to_dashboard=False, watchdog_s=0.3),
                  metrics)
        a.connect()
        try:
            a.kick_watchdog()
            assert ctl.state().watchdog_hz > 0
            ctl.drop_connections(down_s=1.0)
            _wait(lambda: not a.is_connected(), timeout=3.0, what="disconnect noticed")
            time.sleep(1.1)
            assert a.reconnect()
            s = ctl.wait_for(lambda s: s.control_script_running, timeout=3.0, what="the script back")
            # No kick follows (a blind daemon): the controller ends the script within its period.
            s = ctl.wait_for(lambda s: not s.control_script_running, timeout=3.0, what="the watchdog expiring")
            assert s.last_stop_kind == "watchdog"
        finally:
            a.close()
