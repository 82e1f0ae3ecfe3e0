"""deploy/: the Grafana dashboard and the Prometheus alert rules use only metrics a running daemon serves.

A real ``slipd run`` (the packaged model, the emulated PapillArray and MX-28 on ptys) serves its metrics
on loopback; the test provokes dropped frames and a sensor stall, scrapes the endpoint over HTTP and
checks that every metric name in the dashboard and in the alert rules is in the scrape.
"""

from __future__ import annotations

import json
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import yaml

from slipd.recording import Recording

ROOT = Path(__file__).resolve().parents[1]
DASHBOARD = ROOT / "deploy" / "grafana" / "slipd.json"
ALERTS = ROOT / "deploy" / "prometheus" / "slipd-alerts.yml"

PROMQL_KEYWORDS = {"and", "or", "unless", "by", "without", "on", "ignoring", "group_left", "group_right", "bool",
                   "offset", "inf", "nan"}


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression reads: identifiers that are not functions, keywords, label
    names or values, or range durations (Grafana's ``$variables`` sit in matchers and ranges)."""
    e = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # strings (label values)
    e = re.sub(r"\{[^}]*\}", "", e)  # label matchers
    e = re.sub(r"\[[^\]]*\]", "", e)  # range durations
    e = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", e)  # grouping labels
    names = set()
    for m in re.finditer(r"(?<![\w.$])[A-Za-z_:][\w:]*", e):
        if e[m.end():].lstrip().startswith("(") or m.group(0).lower() in PROMQL_KEYWORDS:
            continue  # a function call or an operator
        names.add(m.group(0))
    return names


def test_metric_names_parser():
    expr = 'histogram_quantile(0.99, sum by (instance, le) (rate(slipd_x_bucket{a=~"b|c"}[$__rate_interval]))) > 5e-3'
    assert metric_names(expr) == {"slipd_x_bucket"}
    assert metric_names('rate(a_total[1m]) == 0 or sum by (reason) (increase(b_total{reason=~"s_.*"}[5m])) > 0') == {
        "a_total", "b_total"}
    assert metric_names("absent(slipd_ready{job=\"slipd\"})") == {"slipd_ready"}
    assert metric_names("label_values(slipd_ready, instance)") == {"slipd_ready", "instance"}  # see _dashboard_exprs


def _alert_rules() -> list[dict]:
    doc = yaml.safe_load(ALERTS.read_text())
    return [rule for group in doc["groups"] for rule in group["rules"]]


def _dashboard_exprs() -> list[str]:
    dash = json.loads(DASHBOARD.read_text())
    exprs = [t["expr"] for p in dash["panels"] for t in p.get("targets", [])]
    exprs += [a["expr"] for a in dash["annotations"]["list"] if "expr" in a]
    for var in dash["templating"]["list"]:
        query = var.get("query")
        if isinstance(query, dict):
            # label_values(METRIC, LABEL): the metric is read; the label is not a metric name.
            m = re.fullmatch(r"label_values\((\w+),\s*\w+\)", query["query"])
            assert m, query
            exprs.append(m.group(1))
    return exprs


def test_alert_rules_cover_the_failure_modes():
    rules = _alert_rules()
    names = {r["alert"] for r in rules}
    assert {"SlipdSensorStalled", "SlipdFramesDropped", "SlipdFailsafeStop", "SlipdReactionLatencyHigh",
            "SlipdLoopOverruns"} <= names
    for rule in rules:
        assert rule["labels"]["severity"] in ("warning", "critical"), rule["alert"]
        assert rule["annotations"]["summary"] and rule["expr"].strip()
        assert re.fullmatch(r"\d+[smh]", rule.get("for", "0m")), rule["alert"]
    by_name = {r["alert"]: r["expr"] for r in rules}
    assert "slipd_reaction_latency_seconds_bucket" in by_name["SlipdReactionLatencyHigh"]
    assert "0.99" in by_name["SlipdReactionLatencyHigh"] and "0.005" in by_name["SlipdReactionLatencyHigh"]
    assert "slipd_loop_overruns_total" in by_name["SlipdLoopOverruns"]
    assert "slipd_dropped_frames_total" in by_name["SlipdFramesDropped"]


def test_dashboard_is_well_formed():
    dash = json.loads(DASHBOARD.read_text())
    ids = [p["id"] for p in dash["panels"]]
    assert len(ids) == len(set(ids)) and len(ids) >= 10
    for p in dash["panels"]:
        assert {"x", "y", "w", "h"} <= set(p["gridPos"]) and p["gridPos"]["x"] + p["gridPos"]["w"] <= 24
        refs = [t["refId"] for t in p.get("targets", [])]
        assert len(refs) == len(set(refs)), p["title"]
    titles = " ".join(p["title"].lower() for p in dash["panels"])
    for topic in ("frames", "reaction latency", "fail-safe", "overruns", "slip probability"):
        assert topic in titles


def _referenced() -> set[str]:
    names = set()
    for expr in [*_dashboard_exprs(), *(r["expr"] for r in _alert_rules())]:
        names |= metric_names(expr)
    return names


def test_deploy_files_use_only_slipd_metrics():
    names = _referenced()
    assert len(names) >= 15
    assert all(n.startswith("slipd_") for n in names), sorted(n for n in names if not n.startswith("slipd_"))


def _scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as resp:
        return resp.read().decode()


def _exposed(text: str) -> tuple[set[str], dict[str, float]]:
    """Names a query can select in this scrape (samples, plus the series of families that have no sample
    yet: a labelled counter before its first increment), and the unlabelled sample values."""
    names, values = set(), {}
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split()
            names |= {f"{name}_bucket", f"{name}_count", f"{name}_sum"} if kind == "histogram" else {name}
        elif line and not line.startswith("#"):
            series, value = line.rsplit(" ", 1)
            name = series.split("{", 1)[0]
            names.add(name)
            values[series] = float(value)
    return names, values


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_every_referenced_metric_exists_in_a_running_daemon(tmp_path):
    from slipd.sim.devices.mx28 import EmulatedMX28
    from slipd.sim.devices.papillarray import EmulatedPapillArray

    rng = np.random.default_rng(0)
    n = 20000
    rec = Recording(t_us=np.arange(n) * 1000, force=rng.normal(0, 0.01, (n, 9, 3)).astype(np.float32),
                    disp=np.zeros((n, 9, 3)))
    port = _free_port()
    with EmulatedMX28() as servo, EmulatedPapillArray(rec, loop=True) as sensor:
        cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
        cfg["model"].update(manifest="slip_ensemble_int8", detector="onnx")  # the packaged model, by name
        cfg["sensor"]["port"] = sensor.port
        cfg["gripper"]["port"] = servo.port
        cfg["gripper"]["packet_timeout_ms"] = 200  # the emulated servo is a thread of this busy process
        cfg["arm"]["enabled"] = False
        cfg["reaction"].update(actions=["tighten_gripper"], on_failsafe="log_only")  # no arm on this bench
        cfg["recorder"]["enabled"] = False
        cfg["metrics"] = {"enabled": True, "host": "127.0.0.1", "port": port}
        path = tmp_path / "slipd.yaml"
        path.write_text(yaml.safe_dump(cfg))
        proc = subprocess.Popen([sys.executable, "-m", "slipd", "run", "--config", str(path)],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            sensor.start()
            deadline = time.monotonic() + 90
            values: dict[str, float] = {}
            while time.monotonic() < deadline and values.get("slipd_ready") != 1.0:
                assert proc.poll() is None, proc.stdout.read()
                time.sleep(0.2)
                try:
                    _, values = _exposed(_scrape(port))
                except OSError:
                    continue  # not listening yet
            assert values.get("slipd_ready") == 1.0, "the daemon never became ready"
            sensor.jump_counter(5)  # five frames missing by the packet counter
            time.sleep(0.5)
            sensor.stall(400)  # longer than the stall timeout: a fail-safe, counted by reason
            deadline = time.monotonic() + 30  # its own wait: a slow start on a loaded machine must not use it up
            while time.monotonic() < deadline:
                names, values = _exposed(_scrape(port))
                if (values.get("slipd_dropped_frames_total", 0) > 0
                        and any(s.startswith("slipd_failsafe_stops_total{") for s in values)):
                    break
                time.sleep(0.2)
            text = _scrape(port)
        finally:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out[-2000:]
    names, values = _exposed(text)
    assert values["slipd_frames_received_total"] > 1000 and values['slipd_decisions_total{sensor="0"}'] > 0
    assert values["slipd_dropped_frames_total"] >= 5
    # The stall is a fail-safe counted by reason: sensor_stall. Once in a clean-clone CI run (a loaded
    # 2-core machine) it was counted as no_decisions: the last frames before the stall were read, and stamped fresh,
    # late, so the decision's deadline passed first. The supervisor now names a stream that stopped short of the
    # decision a stall (test_liveness asserts that deterministically); this timing-bound test still accepts either.
    assert any(s.startswith("slipd_failsafe_stops_total{") and ('reason="sensor_' in s or 'no_decisions' in s)
               for s in values), [s for s in values if "failsafe" in s]
    missing = sorted(_referenced() - names)
    assert missing == [], f"deploy/ references metrics the daemon does not serve: {missing}"
