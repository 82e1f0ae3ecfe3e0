"""Write reports/reliability.md: every fault slipd meets, what it does, what counts it, which test proves it.

    python tools/reliability_report.py                                   # fuzz 100 000 + 100 000, soak 600 s
    python tools/reliability_report.py --fuzz-pts 20000 --fuzz-config 5000 --soak-seconds 60 --random-model
    python tools/reliability_report.py --soak-json soak.log   # the soak's figures from a finished soak_live --json run

The fault table is data (``FAULTS`` below); each test node id in it is checked to exist in its file
(parsed, not imported) before anything is written, so the report cannot cite a test that is gone. The
figures come from running, in this process and with the sizes given: ``tools/fuzz_pts.py`` (PTSCOM
decoder), ``tools/fuzz_config.py`` (configuration loader) and ``tools/soak_live.py`` (live daemon at
1 kHz against the emulated devices). Exit status 1 when a run failed its own check (the report is
written all the same, saying so).
"""

from __future__ import annotations

import argparse
import ast
import datetime as dt
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from sliplab.paths import ROOT

if TYPE_CHECKING:
    from sliplab.soak_live import SoakReport


@dataclass(frozen=True)
class Fault:
    """One row of the table."""

    fault: str
    behaviour: str
    metric: str
    tests: tuple[str, ...]


F = "tests/daemon/test_faults.py::"
L = "tests/daemon/test_liveness.py::"
R = "tests/daemon/test_reaction.py::"
S = "tests/daemon/test_run_signals.py::"
FAULTS: tuple[Fault, ...] = (
    Fault("Sensor stream stalls (no frame for `sensor.stall_timeout_ms`)",
          "Blind: one fail-safe per episode (stop the arm, policy `reaction.on_failsafe`; keep the grip), one "
          "log line; systemd watchdog pings and the arm's watchdog kicks pause; live again at the first valid "
          "decision on fresh frames",
          '`slipd_failsafe_stops_total{reason="sensor_stall"}`, `slipd_live`',
          (F + "test_sensor_stall_fails_safe_stops_the_arm_and_the_stream_resumes",
           "tests/io/test_sensor.py::test_stall_then_resume_without_gap")),
    Fault("Sensor silent from start-up (port open, no frame ever)",
          "Fail-safe once within the stall timeout of the loop's start; `READY=1` is never sent and the systemd "
          "watchdog never pinged; a sensor that starts streaming "
          "later gets `READY=1` at the first live decision",
          '`slipd_failsafe_stops_total{reason="sensor_silent"}`, `slipd_live` 0',
          ("tests/daemon/test_liveness.py::test_silent_sensor_from_start_up_fails_safe_and_never_reports_ready",
           "tests/daemon/test_liveness.py::test_a_sensor_that_starts_late_still_gets_ready_reported_once_live")),
    Fault("Frames while the sensor zeroes itself (`tare: bias_command`, start-up and after a reconnect)",
          "Not decided on: no alarm or grip command from them; live only after a decision on frames after the bias",
          "(`slipd_live` stays 0 until then)",
          ("tests/daemon/test_liveness.py::test_frames_while_the_sensor_zeroes_itself_at_start_up_are_not_decided_on",)),
    Fault("Every frame carries the same packet counter",
          "Repeats are dropped by the reader (not passed on as discontinuities that restarted the detector on "
          "every frame); no fresh sample within the stall timeout: fail-safe once, pings and arm kicks stop; "
          "recovery when the counter advances",
          '`slipd_failsafe_stops_total{reason="sensor_counter_stuck"}`, '
          '`slipd_frame_errors_total{kind="repeated_counter"}`',
          ("tests/daemon/test_liveness.py::test_blind_stream_fails_safe_once_stops_the_pings_and_the_arm_watchdog_then_"
           "recovers",
           "tests/io/test_sensor.py::test_encoded_frames_are_what_the_emulator_sends")),
    Fault("Valid frames full of NaN / +Inf (PTSCOM carries float32)",
          "The feature stage bridges up to 5 ms by holding the last value; a longer run is blind: fail-safe "
          "once, decisions on held values no longer count as live",
          '`slipd_failsafe_stops_total{reason="sensor_nonfinite"}`, `slipd_nonfinite_values_total`',
          ("tests/daemon/test_liveness.py::test_blind_stream_fails_safe_once_stops_the_pings_and_the_arm_watchdog_then_"
           "recovers",)),
    Fault("Bit-identical frames (a frozen sensor; a real one is never noise-free)",
          "No fresh sample within the stall timeout: fail-safe once, pings and arm kicks stop",
          '`slipd_failsafe_stops_total{reason="sensor_frozen"}`',
          ("tests/daemon/test_liveness.py::test_blind_stream_fails_safe_once_stops_the_pings_and_the_arm_watchdog_then_"
           "recovers",)),
    Fault("slipd killed (SIGKILL, OOM), frozen (SIGSTOP) or aborted by systemd's watchdog (SIGABRT) while the "
          "arm moves",
          "ur_rtde's controller-side watchdog (`setWatchdog(1 / arm.watchdog_s)`, kicked from the arm thread only "
          "while live) halts the arm and ends the control script within `arm.watchdog_s` of the last kick"
          ". Dashboard stop modes upload no script and have no such watchdog",
          "(the controller's stop; `slipd_device_errors_total{device=\"arm\",kind=\"watchdog\"}` for failed kicks)",
          ("tests/daemon/test_watchdog.py::test_a_dead_or_frozen_daemon_halts_the_moving_arm_within_the_watchdog_period",
           "tests/io/test_arm.py::test_upper_range_registers_and_watchdog")),
    Fault("Sensor USB cable pulled / port hang-up",
          "One fail-safe stop at once; the stall that follows is the same episode"
          "; reader retries with exponential backoff; on replug the port reopens, "
          "the detector restarts (features, GRU state, decision) and decisions resume",
          '`slipd_failsafe_stops_total{reason="sensor_lost"}`, `slipd_reconnects_total{device="sensor"}`',
          (F + "test_sensor_unplug_fails_safe_then_reconnects_and_restarts_the_detector",
           "tests/io/test_sensor.py::test_unplug_disconnects_and_replug_reconnects")),
    Fault("Sensor controller power-cycled (its rate and bias back at their defaults)",
          "On the reconnect the daemon sends the rate again and, with `tare: bias_command`, the bias; frames "
          "until `sensor.bias_timeout_s` are not decided on; live again after a valid decision, one fail-safe "
          "for the whole episode",
          '`slipd_reconnects_total{device="sensor"}`, `slipd_live`',
          (F + "test_a_power_cycled_sensor_is_zeroed_again_after_the_reconnect",)),
    Fault("Sensor controller power-cycled mid-grasp (the bias after the reconnect takes the held load for the zero)",
          "Armed at the reconnect when a finger was in contact as the sensor went; once no finger is in contact and "
          "every pillar has stayed still for 0.3 s with a finger's normal force at least half its grip at the loss "
          "below the zero (the jaw let go), that free air becomes the zero in software (`slipd.daemon.rezero`): "
          "no blind spell, no fail-safe, logged when armed and when done; a grip that only eased, or a jaw still "
          "opening, is not taken for the free air; any later bias drops the software zero (the sensor zeroed itself)",
          "`slipd_sensor_rezeros_total`",
          (F + "test_a_sensor_zeroed_under_a_grasp_is_zeroed_again_in_software_once_the_jaw_lets_go",
           "tests/daemon/test_rezero.py::test_a_grip_that_only_eased_and_a_grasp_in_contact_are_not_the_free_air")),
    Fault("Garbage bytes between frames",
          "Skipped while resynchronising on the start marker; next frames decoded",
          "`slipd_garbage_bytes_total`",
          (F + "test_corrupt_frames_are_counted_and_later_frames_processed",
           "tests/io/test_pts.py::test_garbage_bytes_are_counted_exactly")),
    Fault("Truncated frame / wrong length / bad checksum",
          "Frame counted and skipped, never raised; the frames after it are processed; its consumed counter "
          "shows as one dropped frame",
          "`slipd_frame_errors_total{kind=...}` (kinds `bad_checksum`, `bad_length`, `bad_structure`), "
          "`slipd_dropped_frames_total`",
          (F + "test_corrupt_frames_are_counted_and_later_frames_processed",
           "tests/io/test_pts.py::test_truncated_frame_followed_by_a_good_one",
           "tests/io/test_pts.py::test_bad_checksum_is_counted_and_skipped",
           "tests/io/test_pts.py::test_wrong_length_is_counted_and_skipped")),
    Fault("Packet counter jumps forward (frames lost on the link)",
          "Gap counted; stream continues without a restart",
          "`slipd_dropped_frames_total`",
          (F + "test_corrupt_frames_are_counted_and_later_frames_processed",
           "tests/io/test_sensor.py::test_counter_jump_and_backwards_counter")),
    Fault("Packet counter goes backwards (controller reset)",
          "Discontinuity: the detector restarts (no filter/GRU history across the break)",
          '`slipd_frame_errors_total{kind="discontinuity"}`',
          (F + "test_corrupt_frames_are_counted_and_later_frames_processed",
           "tests/io/test_sensor.py::test_counter_jump_and_backwards_counter")),
    Fault("Burst: 10 000 frames arrive at once",
          "All processed in order, none lost; the loop catches up (time printed by the test)",
          "`slipd_frames_received_total`, `slipd_loop_overruns_total`",
          (F + "test_burst_of_frames_is_processed_without_loss",
           "tests/io/test_sensor.py::test_burst_of_10000_frames_without_loss")),
    Fault("Gripper servo silent while tightening",
          "dynamixel-sdk times out after the retries -> GripperError -> the reaction falls back to stopping the "
          "arm whatever the policy",
          '`slipd_device_errors_total{device="gripper",kind="reaction"}`, '
          '`slipd_failsafe_stops_total{reason="tighten_gripper failed"}`',
          (F + "test_servo_silent_while_tightening_falls_back_to_stopping_the_arm",
           "tests/daemon/test_reaction.py::test_gripper_failure_falls_back_to_arm_stop",
           "tests/io/test_gripper.py::test_a_short_silence_is_bridged_by_retries")),
    Fault("Servo answers again after a tighten failed",
          "The failed tighten is owed until the grasp ends and sent again when the health poll hears the "
          "servo; under grip_control the fail-safe's grip at the object's limit is owed as "
          "itself",
          "(reaction log; `slipd_device_errors_total{device=\"gripper\",kind=\"reaction\"}` for the failure)",
          (F + "test_tighten_lost_while_the_servo_was_silent_is_retried_when_it_answers",
           "tests/daemon/test_reaction.py::test_failed_tighten_is_owed_and_retried_once_the_servo_answers",
           "tests/daemon/test_reaction.py::test_grip_controls_failsafe_grip_is_owed_as_itself_not_as_a_tighten")),
    Fault("A gripper call hangs in the vendor library (a status poll, or a grip command it waits behind)",
          "After 2 s it is a gripper fault: one fail-safe, logged"
          "; healthy again once the call returns",
          '`slipd_failsafe_stops_total{reason="gripper_fault"}`, '
          '`slipd_device_errors_total{device="gripper",kind="unhealthy"}`',
          (L + "test_a_gripper_call_that_hangs_is_a_gripper_fault",)),
    Fault("Gripper hardware error (overload) or torque off, seen by the health poll (every 0.5 s)",
          "Fail-safe stop once per occurrence (not per poll); no automatic reboot (it would drop the object)",
          '`slipd_failsafe_stops_total{reason="gripper_fault"}`, '
          '`slipd_device_errors_total{device="gripper",kind="unhealthy"}`',
          (F + "test_servo_hardware_error_seen_by_the_health_poll_fails_safe",
           "tests/io/test_gripper.py::test_overload_is_reported_and_recovered")),
    Fault("Servo power blip (its supply dips, the USB adapter stays up): back with torque off and no error",
          "A tighten sent then fails (torque read after the bytes left): owed, fail-safe; commands are refused while "
          "torque is known off, and slipd never switches it on unasked",
          '`slipd_failsafe_stops_total{reason="tighten_gripper failed"}`, '
          '`slipd_device_errors_total{device="gripper",kind="reaction"}`',
          ("tests/io/test_gripper.py::test_a_power_blip_makes_the_next_tighten_fail_and_stay_failed",
           "tests/io/test_gripper.py::test_torque_off_servo_ignores_goals")),
    Fault("Gripper USB adapter unplugged and plugged back (same device path)",
          "The I/O error drops the port; the health task reopens it with back-off (0.25 s doubling to 5 s), writing "
          "nothing, and an owed tighten goes out once the servo holds",
          '`slipd_reconnects_total{device="gripper"}`, `slipd_device_errors_total{device="gripper",kind="io"}`',
          (L + "test_an_unplugged_gripper_adapter_is_reopened_and_the_owed_tighten_sent",
           "tests/io/test_gripper.py::test_an_unplugged_adapter_drops_the_port_and_reconnect_reopens_it_without_torque")),
    Fault("Servo EEPROM limits narrower than the config (PWM Limit, position or angle limits, 1.0 wheel mode)",
          "`slipd run` exits 5 at start-up naming the key and the limit, before torque is switched on",
          "(exit status)",
          ("tests/io/test_gripper.py::test_connect_refuses_settings_beyond_the_servos_own_limits",)),
    Fault("slipd restarts (systemd after a crash, a person) while the jaw holds an object it secured",
          "The start-up grip keeps the goal and effort it finds while the jaw presses on an object (torque on, "
          "position mode, the goal at or past the hold position, loaded >= 5 %; an empty jaw gets the hold setting), "
          "and a graded tighten never goes below that level; with the jaw found gripping no start-up bias is sent (the "
          "sensor's zero from before stands; tare: startup logs that its zero holds the load)",
          "(log line)",
          ("tests/io/test_gripper.py::test_a_restart_mid_grasp_keeps_the_tighter_grip_it_finds",
           R + "test_a_graded_tighten_never_goes_below_the_grip_found_at_start_up",
           L + "test_a_restart_that_finds_the_jaw_gripping_keeps_the_sensors_zero",
           L + "test_the_daemons_start_up_keeps_a_grip_it_secured_before_a_restart",
           "tests/io/test_gripper.py::test_a_restart_keeps_a_grip_controls_low_effort_and_an_empty_jaw_gets_the_hold")),
    Fault("The object leaves the jaw while a tighten is owed (the servo silent during the alarm)",
          "No finger in contact: the grasp has ended and what was owed to it is dropped, also a tighten in flight "
          "that fails later; an owed arm stop stays owed",
          "(log line)",
          (L + "test_a_tighten_owed_to_a_grasp_that_let_go_is_not_sent_to_the_next",
           R + "test_a_tighten_that_fails_after_its_grasp_let_go_is_not_owed")),
    Fault("A later graded alarm of lower risk (reaction.graded)",
          "The grip never loosens: the highest level sent for the grasp (1 after a secure or a fail-safe's tighten) "
          "stands, an owed lower tighten is retried at it",
          "(reaction records)",
          ("tests/daemon/test_reaction.py::test_graded_grip_never_loosens_after_a_secure_or_until_a_new_grasp",
           "tests/daemon/test_reaction.py::test_rearm_window_suppresses_repeats_but_graded_escalates")),
    Fault("A device call's outcome arrives on the device's thread (a failed tighten's fail-safe, an owed command)",
          "Handled on the loop's thread while the daemon runs (`Reaction.post`), so the stop in flight, what is owed "
          "and the grip controller's fail-safe target change on one thread",
          "(reaction log)",
          ("tests/daemon/test_reaction.py::test_device_outcomes_are_handled_on_the_loops_thread_while_the_daemon_runs",
           L + "test_frames_while_the_sensor_zeroes_itself_at_start_up_are_not_decided_on")),
    Fault("SIGTERM or SIGINT during start-up (devices opening, the arm's control script just uploaded, the sensor "
          "zeroing itself)",
          "Held back while the devices open, then the devices are closed (the control script ended) and `slipd run` "
          "exits 0; during the bias "
          "wait (`sensor.bias_timeout_s`, up to 30 s) the stop ends the wait",
          "(exit status)",
          ("tests/daemon/test_cli_run.py::test_a_stop_during_start_up_ends_the_arms_control_script",
           L + "test_a_stop_during_the_start_up_bias_wait_ends_it")),
    Fault("A second SIGTERM or SIGINT while the devices close, or a device thread hung at shutdown",
          "Ignored (logged) during the close; the arm is closed first and both device threads share one 5 s deadline, "
          "under systemd's 10 s TimeoutStopSec",
          "(log)",
          (L + "test_close_ends_the_arm_first_and_waits_once_for_a_hung_gripper",)),
    Fault("Sensor port present but not openable at start-up (held by another process, not a tty)",
          "`slipd run` exits 5 with one line",
          "(exit status)",
          ("tests/daemon/test_cli_run.py::test_a_sensor_port_that_cannot_be_opened_exits_5_in_one_line",)),
    Fault("Supervision or the device health task crashes",
          "Logged, one fail-safe, the daemon stops and `slipd run` exits 1 for systemd to restart it",
          '`slipd_failsafe_stops_total{reason="internal_error"}`',
          (L + "test_a_crash_of_the_health_task_fails_safe_and_stops_the_daemon",)),
    Fault("Sensor port missing at start-up",
          "`slipd run` exits 5 with one line naming `sensor.port`, no traceback, before the gripper or the arm "
          "is opened",
          "(exit status)",
          ("tests/daemon/test_cli_run.py::test_missing_sensor_port_exits_5_in_one_line_before_any_device_is_opened",)),
    Fault("Gripper unplugged at start-up / absent id",
          "`slipd run` refuses to start (exit 5, names the device); the driver retries then raises",
          '`slipd_device_errors_total{device="gripper",kind=...}`',
          ("tests/io/test_gripper.py::test_absent_id_retries_then_raises",
           "tests/io/test_gripper.py::test_unplugged_servo_then_back")),
    Fault("UR protective stop",
          "Noticed by the arm health poll (every 150 ms) and logged once; never unlocked by slipd; the stop "
          "command reports it instead of failing silently",
          '`slipd_device_errors_total{device="arm",kind="protective_stop"}` (once per occurrence)',
          (F + "test_arm_protective_stop_and_link_loss_are_noticed_and_the_link_comes_back",
           "tests/io/test_arm.py::test_protective_stop_detected_and_commands_fail")),
    Fault("UR controller drops the RTDE connection",
          "Noticed by the health poll, logged; reconnect on the arm thread with backoff (0.25 s .. 5 s); "
          "healthy again after the reconnect",
          '`slipd_device_errors_total{device="arm",kind="disconnected"}`, `slipd_reconnects_total{device="arm"}`',
          (F + "test_arm_protective_stop_and_link_loss_are_noticed_and_the_link_comes_back",
           "tests/io/test_arm.py::test_disconnect_detected_and_reconnect_works")),
    Fault("UR refuses the stop command",
          "Falls back to the dashboard `stop`; when that fails too the stop is a failed reaction (recorded, logged) "
          "and owed: sent again on every arm health poll that reaches the controller until "
          "one is taken or a protective stop halted the arm",
          '`slipd_device_errors_total{device="arm",kind="stop_failed"}`, '
          '`slipd_device_errors_total{device="arm",kind="reaction"}`',
          ("tests/io/test_arm.py::test_refused_stop_falls_back_to_dashboard_and_reconnect_reuploads",
           R + "test_a_refused_arm_stop_is_a_failure_owed_until_the_controller_takes_one",
           L + "test_the_health_polls_retry_an_owed_tighten_and_an_owed_arm_stop")),
    Fault("Fail-safes while an arm stop hangs (a dashboard fallback waiting on a controller that does not answer); "
          "a silent servo under grip_control",
          "One arm stop in flight: the others join it; grip_control "
          "fails safe once per run of failed grip commands",
          '`slipd_failsafe_stops_total`',
          (R + "test_one_arm_stop_in_flight_however_many_fail_safes",
           "tests/daemon/test_grip_control.py::test_a_run_of_failed_grip_commands_fails_safe_once")),
    Fault("RTDE link drops and comes back (slipd's reconnect, or ur_rtde's own)",
          "The control script a reconnect uploads is watched at once"
          "; the watchdog is set again every 20 kicks",
          '`slipd_device_errors_total{device="arm",kind="watchdog"}` (a failed kick)',
          ("tests/io/test_arm.py::test_a_script_uploaded_by_a_reconnect_is_watched_at_once",)),
    Fault("Configuration edit breaks YAML / unknown key / out-of-range value",
          "`slipd run` / `check-config` refuse with exit 3, naming file, line or key path and reason; no device "
          "is touched",
          "(exit status; fuzzed below)",
          ("tests/config/test_config.py::test_broken_yaml_names_line_and_column",
           "tests/config/test_config.py::test_unknown_keys_rejected_with_suggestion",
           "tests/config/test_config.py::test_numbers_are_read_as_yaml_1_2_and_a_boolean_is_no_number",
           "tests/config/test_config.py::test_keys_that_the_chosen_mode_never_reads_are_refused",
           "tests/config/test_config.py::test_check_config_and_run_read_a_heuristics_parameters_before_any_device",
           "tests/config/test_config.py::test_an_unusable_recorder_directory_is_refused_before_any_device",
           "tests/config/test_config.py::test_check_config_exit_codes",
           "tests/config/test_config.py::test_fuzz_short")),
    Fault("Model file half-copied / wrong hash / wrong shapes",
          "Refused before any device is opened (exit 4)",
          "(exit status)",
          ("tests/daemon/test_cli_run.py::test_bad_model_is_refused_before_any_device_is_opened",
           "tests/detect/test_ensemble.py::test_truncated_onnx",
           "tests/detect/test_ensemble.py::test_wrong_hash")),
    Fault("Non-finite model input or output",
          "Window refused / stream state reset; counted as a step error, no alarm from garbage",
          "`LoopStats.step_errors` (no Prometheus metric; see the note below the table)",
          ("tests/detect/test_ensemble.py::test_nonfinite_window_is_refused_and_state_untouched",
           "tests/detect/test_ensemble.py::test_nonfinite_output_resets_the_stream")),
    Fault("Alarm latched high for minutes",
          "One recording per alarm episode, extended while the alarm stays high and bounded at 30 s after the "
          "onset; no new file until the alarm falls, so the recording holding the onset is kept",
          "(recorder log)",
          ("tests/daemon/test_recorder.py::test_latched_alarm_for_10_minutes_writes_one_bounded_recording_and_keeps_it",
           "tests/daemon/test_recorder.py::test_alarm_that_stays_high_extends_one_recording_beyond_the_ring",
           "tests/daemon/test_recorder.py::test_a_latched_alarm_on_one_finger_is_one_recording_whatever_the_other_says")),
    Fault("Fail-safe while an alarm's recording waits for its frames after",
          "The recording names the fail-safe and, when no frame may follow (a stalled sensor), is written at once"
          "; a "
          "fail-safe's recording carries the tare offset the daemon used, as an alarm's does (replay re-tared)",
          "(recorder log; `trigger.events` in the recording)",
          ("tests/daemon/test_recorder.py::test_a_fail_safe_during_an_alarm_recording_writes_it_at_once_and_names_it",
           "tests/daemon/test_liveness.py::test_a_fail_safe_recording_carries_the_tare_offset_the_daemon_used")),
    Fault("`metrics.host` other than loopback",
          "Accepted with a start-up warning naming the exposure (every interface for 0.0.0.0)",
          "(log)",
          ("tests/daemon/test_cli_run.py::test_running_daemon_never_imports_torch",
           "tests/daemon/test_cli_run.py::test_metrics_exposure_names_who_can_scrape")),
    Fault("ur_rtde prints to stdout/stderr (link drops, reconnects)",
          "Its lines go through the log (`slipd.ur_rtde`, in the log format)",
          "(log)",
          ("tests/daemon/test_watchdog.py::test_ur_rtde_output_goes_through_the_log",)),
    Fault("Crash or full disk while writing a recording",
          "No valid-looking partial file; slow disk drops recordings rather than queueing without bound",
          "(recorder log)",
          ("tests/daemon/test_recorder.py::test_crash_mid_write_leaves_no_valid_looking_file",
           "tests/daemon/test_recorder.py::test_slow_disk_drops_recordings_instead_of_queueing_without_bound",
           "tests/daemon/test_recorder.py::test_a_failed_write_leaves_no_staging_file_and_the_size_bound_still_holds")),
    Fault("A hung disk at shutdown, the state directory removed, the clock behind after a reboot",
          "close keeps to one deadline for all pending writes"
          "; a removed directory comes back with mode 0750; the size bound deletes an "
          "earlier run's recordings before this run's",
          "(recorder log)",
          ("tests/daemon/test_recorder.py::test_close_keeps_to_its_timeout_whatever_is_pending",
           "tests/daemon/test_recorder.py::test_a_state_directory_removed_while_running_comes_back_with_its_mode",
           "tests/daemon/test_recorder.py::test_the_size_bound_deletes_an_earlier_runs_recordings_before_this_ones")),
    Fault("A break in the stream (controller restart, reconnect) inside a recording's window; an alarm held past a "
          "short `recorder.seconds_after`",
          "The recording ends at the break and the next starts after it; a lost sensor's fail-safe still holds the "
          "seconds before the loss; an "
          "alarm still up when its recording ends starts no new one until it falls"
          ". The decisions' JSON is built on the "
          "recorder's thread",
          "(recorder log)",
          ("tests/daemon/test_recorder.py::test_a_break_in_the_stream_ends_the_recording_and_the_next_starts_after_it",
           "tests/daemon/test_recorder.py::test_a_lost_sensor_records_what_led_to_it_and_a_later_alarm_starts_after_the_break",
           "tests/daemon/test_recorder.py::test_an_alarm_still_up_when_a_short_recording_ends_starts_no_new_one")),
    Fault("A glitch or a tare drift in free air (the contact gate)",
          "One finite -1e6 N moves the free-air baseline by at most 0.001 N"
          "; a restart on the same tare keeps the drift the baseline followed"
          "; a release forgets the friction estimate after a drift too",
          "(`slipd_decisions_total` rising in free air would show it)",
          ("tests/detect/test_detector.py::test_one_glitch_does_not_hold_the_contact_gate_open",
           "tests/detect/test_detector.py::test_a_restart_keeps_the_drift_the_gate_followed_and_a_tare_under_way_starts_"
           "again",
           "tests/detect/test_detector.py::test_a_release_forgets_the_friction_estimate_even_after_a_drift")),
    Fault("The metrics port in use, the recording directory read-only, a device path missing at start-up",
          "Found before any device is touched (no servo packet, no control script on the arm): one line and an exit "
          "code, 6 for the port, 3 for the directory (a file is written and removed to prove it writable), 5 for a "
          "device; the port is bound there and kept for the run",
          "(exit status)",
          (S + "test_a_busy_metrics_port_exits_6_in_one_line_before_any_servo_packet_or_arm_script",
           S + "test_a_read_only_recording_directory_at_start_up_exits_3_before_any_device",
           "tests/daemon/test_cli_run.py::test_missing_sensor_port_exits_5_in_one_line_before_any_device_is_opened")),
    Fault("SIGHUP (`systemctl reload`, a closed terminal)",
          "The config file is read again and checked as `check-config` does; `decision.*`, `control.log_level`, "
          "`recorder.*` and `sensor.rate_tolerance` are applied between two blocks of frames, any other changed key is "
          "named in one line as needing a restart; a file that fails the check is refused in one line and the daemon "
          "runs on, live",
          "(log)",
          (S + "test_sighup_applies_a_valid_config_names_what_needs_a_restart_and_refuses_an_invalid_one",)),
    Fault("SIGQUIT, SIGUSR1, SIGUSR2 and the other signals whose default ends the process",
          "The SIGTERM path: one log line naming the signal, the arm's control script ended, the grip held, "
          "recordings written, exit 0. SIGPIPE and SIGXFSZ stay ignored (a failed write is handled where it happens); "
          "SIGABRT stays systemd's watchdog abort",
          "(exit status, log)",
          (S + "test_other_stop_signals_take_the_sigterm_path_and_end_the_arms_control_script",)),
    Fault("The sensor streams at another rate than the model's (500 Hz or 2 kHz for a 1 kHz model: it ignored the "
          "rate command)",
          "Measured from the controller's clock and packet counter over 0.2 s of device time, from the first frames "
          "(during the start-up bias wait) and continuously; beyond `sensor.rate_tolerance` the daemon is blind with "
          "cause `rate` (one fail-safe, one line naming both rates), not live and not `READY=1` at start-up; live "
          "again once the rate is back, like any blind episode",
          '`slipd_failsafe_stops_total{reason="rate"}`, `slipd_sensor_rate_hz`',
          (S + "test_a_sensor_at_the_wrong_rate_fails_safe_with_cause_rate_and_is_never_ready",)),
    Fault("The controller's timestamps run backwards (5 s) or jump ahead of its packet counter",
          "Counted per frame, logged once per episode (an episode ends after 0.2 s of regular timestamps); the rate "
          "measurement starts again after it; decisions go on (the counter, not the clock, orders the frames)",
          '`slipd_timestamp_jumps_total{kind="backwards"|"forward"}`',
          (S + "test_timestamps_that_jump_are_counted_and_logged_once_per_episode",)),
    Fault("Frames the controller streamed before slipd read the port (every start)",
          "Counted apart from losses until the first live decision; the dropped-frames alert does not see them",
          "`slipd_frames_discarded_at_start_total` (not `slipd_dropped_frames_total`)",
          (S + "test_frames_missing_before_the_daemon_is_live_are_counted_apart_from_drops",)),
    Fault("The recording directory goes read-only (or the disk fills) while running",
          "Each lost recording is counted by reason and logged in one line without a traceback; the next recording is "
          "tried as usual and written once the directory takes files again",
          "`slipd_recordings_failed_total{reason}` (alert `SlipdRecordingsLost`)",
          (S + "test_a_recording_directory_gone_read_only_counts_each_lost_recording_in_one_line_and_recovers",)),
    Fault("A fail-safe episode with the arm (sensor unplugged and back, three times)",
          "Two lines at WARNING or above per episode (`blind: ...; fail-safe (policy)` and `live again after ...`); "
          "the control script that slipd's own stop ended, and its upload again, are INFO",
          "`slipd_failsafe_stops_total{reason}`",
          (S + "test_a_fail_safe_episode_is_two_lines_and_slipds_own_stop_of_the_arm_is_no_error",)),
    Fault("Hours of 1 kHz input",
          "No frame lost, no decode error (soak below)",
          "`slipd_frames_received_total` vs frames sent",
          (F + "test_soak_30_s_at_1_khz_loses_no_frame",)),
)


def missing_tests(faults: tuple[Fault, ...] = FAULTS, root: Path = ROOT) -> list[str]:
    """Node ids in ``faults`` whose file or test function does not exist."""
    cache: dict[str, set[str]] = {}
    missing = []
    for f in faults:
        for node in f.tests:
            path, _, name = node.partition("::")
            if path not in cache:
                p = root / path
                tree = ast.parse(p.read_text(), str(p)) if p.exists() else None
                cache[path] = set() if tree is None else {
                    n.name for n in tree.body if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)}
            if name not in cache[path]:
                missing.append(node)
    return missing


def table(faults: tuple[Fault, ...] = FAULTS) -> list[str]:
    """The Markdown fault table."""
    out = ["| Fault | Expected behaviour | Counted by | Proved by |", "|---|---|---|---|"]
    for f in faults:
        tests = "<br>".join(f"`{t}`" for t in f.tests)
        out.append(f"| {f.fault} | {f.behaviour} | {f.metric} | {tests} |")
    return out


def soak_from_json(path: Path) -> SoakReport:
    """The ``SoakReport`` of a finished ``tools/soak_live.py --json`` run (the last JSON line of its output)."""
    import json

    from sliplab.soak_live import SoakReport

    line = [x for x in path.read_text().splitlines() if x.startswith("{")][-1]
    d = json.loads(line)
    d.pop("ok", None)
    for k in ("fds", "threads"):
        if k in d:
            d[k] = tuple(d[k])
    return SoakReport(**d)


def soak_command(soak: SoakReport) -> str:
    """The command that reproduces a soak's figures."""
    from sliplab.soak_live import default_warmup

    cmd = f"tools/soak_live.py --seconds {soak.seconds:g}"
    if soak.slip_every_s:
        cmd += f" --slip-every {soak.slip_every_s:g}"
    if soak.failsafe_every_s:
        cmd += f" --failsafe-every {soak.failsafe_every_s:g}"
    if soak.recordings:
        cmd += " --record"
    if soak.warmup_s and soak.warmup_s != default_warmup(soak.seconds):
        cmd += f" --warmup {soak.warmup_s:g}"
    return cmd


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    """Run the fuzzers and the soak with the sizes given and write the report."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fuzz-pts", type=int, default=100_000, help="inputs for tools/fuzz_pts.py (default 100000)")
    p.add_argument("--fuzz-config", type=int, default=100_000, help="documents for tools/fuzz_config.py")
    p.add_argument("--soak-seconds", type=float, default=600.0, help="tools/soak_live.py duration (default 600)")
    p.add_argument("--model", type=Path, default=ROOT / "slipd" / "models" / "slip_ensemble.json",
                   help="model for the soak")
    p.add_argument("--random-model", action="store_true", help="soak a random-weight full-size ensemble")
    p.add_argument("--soak-json", type=Path, default=None,
                   help="take the live soak from this output of `tools/soak_live.py ... --json` (its last JSON line: "
                        "a long soak run beforehand) instead of running one")
    p.add_argument("--note", default="", help="a line added to the report (e.g. why sizes are reduced)")
    p.add_argument("--out", type=Path, default=ROOT / "reports" / "reliability.md")
    args = p.parse_args(argv)

    gone = missing_tests()
    if gone:
        print("the fault table cites tests that do not exist:\n  " + "\n  ".join(gone), file=sys.stderr)
        return 2
    if not args.random_model and not args.model.exists():
        print(f"{args.model}: no such model manifest (pass --model, or --random-model)", file=sys.stderr)
        return 2

    from sliplab import fuzz_config, fuzz_pts, soak_live

    ok = True
    print(f"fuzz_pts -n {args.fuzz_pts} ...", flush=True)
    pts = fuzz_pts.fuzz(args.fuzz_pts, seed=0)
    ok &= pts.ok
    print(f"fuzz_config -n {args.fuzz_config} ...", flush=True)
    t0 = time.perf_counter()
    try:
        cfg_counts, cfg_fail = fuzz_config.run(args.fuzz_config, seed=0), ""
    except Exception as exc:  # an exception other than ConfigError escaped the loader: that is the finding
        cfg_counts, cfg_fail = None, repr(exc)
        ok = False
    cfg_s = time.perf_counter() - t0
    if args.soak_json is not None:
        soak = soak_from_json(args.soak_json)
        args.soak_seconds = soak.seconds
    else:
        print(f"soak_live --seconds {args.soak_seconds:g} ...", flush=True)
        with tempfile.TemporaryDirectory(prefix="slipd-reliability-") as tmp:
            if args.random_model:
                model, threshold = soak_live.random_model(Path(tmp)), 0.999
            else:
                model, threshold = args.model, None
            soak = soak_live.soak(args.soak_seconds, model, threshold=threshold)
    if args.random_model:
        soak.model = "random weights, full-size SlipNet x5 (threshold 0.999; no trained model yet)"
    else:
        soak.model = str(Path(soak.model).resolve().relative_to(ROOT)) if Path(soak.model).is_relative_to(ROOT) \
            else soak.model
    ok &= soak.ok

    full = args.fuzz_pts >= 100_000 and args.fuzz_config >= 100_000 and args.soak_seconds >= 600
    cmd = (f"python tools/reliability_report.py --fuzz-pts {args.fuzz_pts} --fuzz-config {args.fuzz_config} "
           + (f"--soak-json {args.soak_json}" if args.soak_json is not None
              else f"--soak-seconds {args.soak_seconds:g}") + (" --random-model" if args.random_model else ""))
    lines = [
        "# slipd reliability report",
        "",
        f"Generated by `{cmd}` on {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC, commit {_git_commit()}, "
        f"{platform.machine()} with {platform.python_version()} (a shared 2-core machine: timings are noisy).",
        "",
        ("Sizes: the full defaults." if full else
         "Sizes: **reduced** from the defaults (100 000 fuzz inputs each, 600 s soak); run the command without "
         "options for the full report."),
    ]
    if args.note:
        lines += ["", args.note]
    lines += [
        "",
        "## Faults",
        "",
        "Each row: what goes wrong, what slipd does, the Prometheus metric that counts it, and the tests that "
        "prove it (daemon level in `tests/daemon/test_faults.py`, through the emulated devices with the real "
        "pyserial, dynamixel-sdk and ur_rtde clients; driver level elsewhere). Every cited test is checked "
        "to exist when this report is generated.",
        "",
        *table(),
        "",
        "Liveness (`slipd/daemon/loop.py`) is one rule: a valid decision on fresh samples (counter advancing, "
        "finite, not bit-identical to the one before) within `sensor.stall_timeout_ms`. Every blind cause above "
        "fails safe once per episode with one log line and its own `reason`; only while live are the systemd "
        "watchdog pinged and the arm's watchdog kicked, and `READY=1` waits for the first live decision.",
        "",
        "`slipd_nonfinite_values_total` is incremented (non-finite and "
        "clipped sensor values, once per block of frames); PTSCOM carries float32, so NaN and Inf do reach the "
        "daemon from a sensor. Model step errors still have no metric (`LoopStats.step_errors`).",
        "",
        "## Fuzzing",
        "",
        f"**PTSCOM 2.0 decoder** (`tools/fuzz_pts.py -n {args.fuzz_pts}`): {pts.inputs} inputs, "
        f"{pts.bytes_fed} bytes fed in random splits, {pts.frames_found} frames found; intact frames "
        f"{pts.intact_sent} sent, **{pts.intact_missed} missed**, {pts.wrong_values} with wrong values; "
        f"**{pts.exceptions} exceptions**; decoder errors {pts.errors}, garbage bytes {pts.garbage_bytes}; "
        f"{pts.seconds:.1f} s, peak RSS {pts.peak_rss_mib:.0f} MiB. Verdict: {'pass' if pts.ok else 'FAIL'}.",
        "",
    ]
    if cfg_counts is not None:
        lines.append(
            f"**Configuration loader** (`tools/fuzz_config.py -n {args.fuzz_config}`): {cfg_counts['total']} "
            f"documents, {cfg_counts['valid']} valid, {cfg_counts['config_error']} refused with a ConfigError "
            f"({cfg_counts['yaml_syntax']} YAML syntax), **{cfg_counts['escaped']} other exceptions**; "
            f"{cfg_s:.1f} s. Verdict: pass (every bad document refused with a message naming the source).")
    else:
        lines.append(f"**Configuration loader** (`tools/fuzz_config.py -n {args.fuzz_config}`): FAIL: {cfg_fail}")
    lines += [
        "",
        "## Live soak",
        "",
        f"`{soak_command(soak)}`: the daemon "
        + ("alone in its process at 1 kHz against the emulated PapillArray and MX-28 (one process of their own) and "
           "UR controller (another)" if soak.emulators_own_process else
           "in-process at 1 kHz against the emulated PapillArray, MX-28 and UR controller")
        + " (a quiet hold" + (f", the packaged sample slip every {soak.slip_every_s:g} s"
                                      if soak.slip_every_s else "")
        + (f", a fail-safe sensor stall every {soak.failsafe_every_s:g} s" if soak.failsafe_every_s else "")
        + (", the recorder on" if soak.recordings else "") + "; arm and gripper health polls running)."
        + (" Memory, descriptors and threads are the soak process's own ("
           + ("the daemon's alone" if soak.emulators_own_process else "the emulated sensor and servo included")
           + "), read from /proc every 10 s after the warm-up; the slope is a least-squares line through the memory "
           "samples." if soak.samples else ""),
        "",
        "```",
        *soak.lines(),
        "```",
        "",
        f"Verdict: {'pass: no frame lost, no decode or model-step error' if soak.ok else 'FAIL'}. Overruns count "
        "supervision ticks more than `control.max_overrun_ms` late on this shared machine; they do not lose "
        "frames (the reader is event-driven and the counter proves continuity).",
        "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print(f"wrote {args.out}" + ("" if ok else " (with FAILURES)"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
