"""Fuzz ``slipd.config`` with generated YAML documents: nothing but ``ConfigError`` may escape.

    python tools/fuzz_config.py [-n 100000] [--seed 0]

Documents are built by hypothesis from a valid config: keys replaced by values of every YAML type
(including NaN, infinities, huge integers, nested lists and mappings, unicode), keys deleted, unknown
keys and sections added, and the dumped text mutated at random positions with YAML-significant
characters (so syntax errors, tabs, anchors, tags and flow collections are exercised too). Prints the
counts of valid documents, config errors by kind, and of any other exception (which fails the run and
is shrunk by hypothesis to a minimal document).
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from typing import Any

import yaml
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import seed as hseed
from hypothesis import strategies as st

from slipd.config import ConfigError, SlipdConfig, parse_config

BASE: dict[str, Any] = {
    "sensor": {"port": "/dev/ttyACM0", "rate_hz": 1000, "tare": "bias_command"},
    "model": {"manifest": "models/m.json", "stride": 0},
    "decision": {"threshold": 0.5},
    "reaction": {"actions": ["stop_arm", "tighten_gripper"]},
    "gripper": {"port": "/dev/ttyUSB0", "hold_position": 2048, "secure_position": 2600,
                "hold_pwm": 300, "secure_pwm": 700},
    "arm": {"host": "192.168.1.10"},
    "recorder": {"directory": "/tmp/slipd-fuzz", "formats": ["npz"]},
}
SECTIONS = {name: list(f.annotation.model_fields) for name, f in SlipdConfig.model_fields.items()}
YAML_CHARS = [*":-[]{},#&*!|>'\"%@`?\t\n ", "\x00", "\x85", "\u2028", "~", "null", "yes", "0x1F", ".nan"]

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(["stop_arm", "npz", "csv", "startup", "2.0", "1e3", "127.0.0.1", "::1", "$HOME", "~", ""]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=8,
)


@st.composite
def documents(draw: st.DrawFn) -> str:
    """A YAML text: a mutated valid config, or mutated text of one."""
    doc: dict[Any, Any] = {k: dict(v) for k, v in BASE.items()}
    for _ in range(draw(st.integers(0, 4))):
        section = draw(st.sampled_from([*SECTIONS, "bogus"]))
        op = draw(st.sampled_from(["set", "set", "set", "delete_key", "delete_section", "replace_section"]))
        if op == "delete_section":
            doc.pop(section, None)
        elif op == "replace_section":
            doc[section] = draw(values)
        else:
            if not isinstance(doc.get(section), dict):
                doc[section] = {}
            key = draw(st.sampled_from([*SECTIONS.get(section, []), "unknown_key"]))
            if op == "delete_key":
                doc[section].pop(key, None)
            else:
                doc[section][key] = draw(values)
    if draw(st.integers(0, 19)) == 0:
        doc = draw(values)  # the top level itself of any type
    text = yaml.safe_dump(doc, sort_keys=False, allow_unicode=draw(st.booleans()))
    for _ in range(draw(st.integers(0, 3)) if draw(st.booleans()) else 0):
        pos = draw(st.integers(0, len(text)))
        if draw(st.booleans()):
            text = text[:pos] + draw(st.sampled_from(YAML_CHARS)) + text[pos:]
        else:
            text = text[:pos] + text[pos + draw(st.integers(1, 5)):]
    return text


def run(n: int = 100_000, seed: int = 0) -> collections.Counter:
    """Fuzz ``n`` documents; return counts (total, valid, config_error, yaml_syntax, escaped)."""
    counts: collections.Counter = collections.Counter()

    @hseed(seed)
    @settings(max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck),
              phases=[Phase.generate, Phase.shrink])
    @given(documents())
    def one(text: str) -> None:
        counts["total"] += 1
        try:
            parse_config(text, "<fuzz>", base_dir="/tmp")
            counts["valid"] += 1
        except ConfigError as exc:
            counts["config_error"] += 1
            first = exc.problems[0]
            if "YAML syntax error" in first or "YAML error" in first:
                counts["yaml_syntax"] += 1
            if not exc.problems or any(not p.startswith("<fuzz>") for p in exc.problems):
                counts["escaped"] += 1
                raise AssertionError(f"problem line without the source name: {exc.problems}") from None
        except Exception:
            counts["escaped"] += 1
            raise

    one()
    return counts


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=100_000, help="documents to generate (default 100000)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    try:
        counts = run(args.n, args.seed)
    except Exception as exc:
        print(f"FAIL: an exception other than ConfigError escaped: {exc!r}", file=sys.stderr)
        return 1
    dt = time.perf_counter() - t0
    print(f"documents {counts['total']}  valid {counts['valid']}  config_error {counts['config_error']} "
          f"(yaml syntax {counts['yaml_syntax']})  other exceptions {counts['escaped']}  "
          f"in {dt:.1f} s ({1e3 * dt / max(1, counts['total']):.2f} ms each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
