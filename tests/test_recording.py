"""Recording formats: npz and the Contactile SDK CSV layout round-trip without loss."""

import numpy as np
import pytest

from slipd.recording import Recording, RecordingError, read_sdk_csv, sdk_csv_columns, write_sdk_csv


def _rec(n: int = 50) -> Recording:
    rng = np.random.default_rng(1)
    slip = rng.random((n, 9)) > 0.7
    return Recording(
        t_us=np.arange(n) * 1000,
        force=rng.normal(0, 1, (n, 9, 3)),
        disp=rng.normal(0, 0.2, (n, 9, 3)),
        slip=slip,
        label=(slip.any(1) & ~slip.all(1)).astype(np.uint8),
        object_motion=rng.normal(0, 1, (n, 3)),
        meta={"scene": "test", "seed": 3, "events": {"motion_start": 0.01}},
    )


def _same(a: Recording, b: Recording) -> None:
    for name in ("t_us", "force", "disp", "slip", "label", "object_motion"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.meta == b.meta


def test_npz_roundtrip(tmp_path) -> None:
    rec = _rec()
    path = rec.save(tmp_path / "a.npz")
    _same(rec, Recording.load(path))
    assert not list(tmp_path.glob("*.tmp"))


def test_sdk_csv_roundtrip(tmp_path) -> None:
    rec = _rec()
    path = write_sdk_csv(rec, tmp_path / "a.csv")
    header = path.read_text().splitlines()[1].split(",")
    assert header[: len(sdk_csv_columns())] == sdk_csv_columns()
    assert header[1:7] == ["S0_P0_DX", "S0_P0_DY", "S0_P0_DZ", "S0_P0_FX", "S0_P0_FY", "S0_P0_FZ"]
    _same(rec, Recording.load(path))


def test_sdk_csv_without_truth_and_with_unknown_columns(tmp_path) -> None:
    cols = ["T_us", *[f"S0_P{p}_{q}{a}" for p in range(9) for q in "DF" for a in "XYZ"], "S0_Extra"]
    lines = [",".join(cols), ",".join(["1000", *(["0.5"] * 54), "7"])]
    path = tmp_path / "real.csv"
    path.write_text("\n".join(lines) + "\n")
    rec = read_sdk_csv(path)
    assert rec.slip is None and rec.label is None
    assert rec.force.shape == (1, 9, 3) and float(rec.force[0, 4, 2]) == 0.5


def test_bad_files_name_the_file(tmp_path) -> None:
    bad = tmp_path / "broken.csv"
    bad.write_text("T_us,S0_P0_DX\n1,2\n")
    with pytest.raises(RecordingError, match=r"broken\.csv.*missing SDK column"):
        Recording.load(bad)
    with pytest.raises(RecordingError, match=r"^force: shape \(3, 8, 3\), expected \[3, 9, 3\]"):
        Recording(t_us=np.arange(3), force=np.zeros((3, 8, 3)), disp=np.zeros((3, 9, 3)))


def _error(path) -> str:
    """The whole message, checked to be one line starting with the file's name."""
    with pytest.raises(RecordingError) as exc:
        Recording.load(path)
    text = str(exc.value)
    assert "\n" not in text and text.startswith(f"{path}"), text
    return text


def _one_line_error(path) -> str:
    """The message after ``file: ``."""
    text = _error(path)
    assert text.startswith(f"{path}: "), text
    return text[len(f"{path}: ") :]


def _npz(path, **arrays) -> None:
    """Write an .npz as another tool might: any arrays, no checks."""
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def test_npz_that_is_not_a_zip(tmp_path) -> None:
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    assert _one_line_error(junk) == "not an .npz recording (not a zip archive: starts with b'not ')"
    # A bare .npy and a pickle were read by np.load and reported as "pickled data": now the same answer.
    np.save(tmp_path / "bare.npy", np.zeros(3))
    (tmp_path / "bare.npy").rename(tmp_path / "bare.npz")
    assert _one_line_error(tmp_path / "bare.npz").startswith("not an .npz recording (not a zip archive")
    (tmp_path / "empty.npz").write_bytes(b"")
    assert _one_line_error(tmp_path / "empty.npz") == "not an .npz recording (not a zip archive: empty file)"
    # Starts like a zip (this raised zipfile.BadZipFile through the CLI), then garbage.
    (tmp_path / "pk.npz").write_bytes(b"PK\x03\x04garbage")
    assert _one_line_error(tmp_path / "pk.npz").startswith("not an .npz recording (broken zip archive")
    assert _one_line_error(tmp_path / "missing.npz").startswith("cannot read (No such file")


def test_truncated_npz_names_the_archive_or_array(tmp_path) -> None:
    good = _rec(400).save(tmp_path / "good.npz").read_bytes()
    for cut in (len(good) // 3, len(good) - 30):
        path = tmp_path / f"cut{cut}.npz"
        path.write_bytes(good[:cut])
        text = _one_line_error(path)
        assert text.startswith(("not an .npz recording (broken zip archive", "t_us: cannot read", "force: cannot read",
                                "disp: cannot read", "slip: cannot read")), text


def test_npz_meta_not_json(tmp_path) -> None:
    path = tmp_path / "meta.npz"
    _npz(path, t_us=np.arange(3), force=np.zeros((3, 9, 3)), disp=np.zeros((3, 9, 3)), meta=np.array("{scene: x"))
    assert _one_line_error(path).startswith("meta: not JSON: Expecting property name enclosed in double quotes")
    _npz(path, t_us=np.arange(3), force=np.zeros((3, 9, 3)), disp=np.zeros((3, 9, 3)), meta=np.array("[1, 2]"))
    assert _one_line_error(path) == "meta: not a JSON object (got list)"
    _npz(path, t_us=np.arange(3), force=np.zeros((3, 9, 3)), disp=np.zeros((3, 9, 3)), meta=np.zeros(2))
    assert _one_line_error(path) == "meta: not a JSON string (dtype float64, shape (2,))"


def test_npz_timestamps_going_backwards_are_refused(tmp_path) -> None:
    rec = _rec(10)
    t = rec.t_us.copy()
    t[6] = t[4]  # 6000 -> 4000: backwards at sample 6
    path = tmp_path / "back.npz"
    _npz(path, t_us=t, force=rec.force, disp=rec.disp)
    assert _one_line_error(path) == "t_us: goes backwards at sample 6 (5000 -> 4000 us)"
    t[3] = 0
    _npz(path, t_us=t, force=rec.force, disp=rec.disp)
    assert _one_line_error(path) == "t_us: goes backwards at sample 3 (2000 -> 0 us); 2 such samples"
    t = rec.t_us.copy()
    t[5] = t[4]  # a repeated timestamp is not backwards (a sensor clock tick can be coarse)
    _npz(path, t_us=t, force=rec.force, disp=rec.disp)
    assert len(Recording.load(path)) == 10


def test_npz_wrong_shapes_types_and_missing_arrays(tmp_path) -> None:
    path = tmp_path / "shape.npz"
    ok = {"t_us": np.arange(4), "force": np.zeros((4, 9, 3)), "disp": np.zeros((4, 9, 3))}
    cases = [
        ({"force": np.zeros((4, 3, 9))}, "force: shape (4, 3, 9), expected [4, 9, 3] (N from t_us)"),
        ({"disp": np.zeros((5, 9, 3))}, "disp: shape (5, 9, 3), expected [4, 9, 3] (N from t_us)"),
        ({"t_us": np.zeros((4, 2))}, "t_us: shape (4, 2), expected [N]"),
        ({"label": np.zeros(3)}, "label: shape (3,), expected [4]"),
        ({"slip": np.zeros((4, 8))}, "slip: shape (4, 8), expected [4, 9]"),
        ({"object_motion": np.zeros((4, 2))}, "object_motion: shape (4, 2), expected [4, 3]"),
        ({"force": np.full((4, 9, 3), "x")}, "force: not numbers (dtype <U1)"),
        ({"t_us": np.array([0.0, 1.0, np.nan, 3.0])}, "t_us: not a finite number at sample 2"),
    ]
    for change, message in cases:
        _npz(path, **{**ok, **change})
        assert _one_line_error(path) == message
    _npz(path, t_us=np.arange(4), force=np.zeros((4, 9, 3)))
    assert _one_line_error(path) == "missing array(s) disp (has: t_us, force)"


def _csv(path, rows: list[list[str]], meta: str | None = None) -> None:
    cols = ["T_us", *[f"S0_P{p}_{q}{a}" for p in range(9) for q in "DF" for a in "XYZ"]]
    lines = ([f"# slipd-meta {meta}"] if meta is not None else []) + [",".join(cols)]
    path.write_text("\n".join(lines + [",".join(r) for r in rows]) + "\n")


def test_sdk_csv_broken_files_name_line_and_column(tmp_path) -> None:
    path = tmp_path / "log.csv"
    row = lambda t: [str(t), *(["0.5"] * 54)]  # noqa: E731
    _csv(path, [row(1000), row(2000), row(1500)])
    assert _one_line_error(path) == "T_us: goes backwards at sample 2 (2000 -> 1500 us)"
    _csv(path, [row(1000), row(2000)], meta="{not json")
    assert _error(path).startswith(f"{path}:1: meta: not JSON: ")
    bad = row(2000)
    bad[7] = "1.2.3"
    _csv(path, [row(1000), bad])
    assert _error(path) == (
        f"{path}:3: S0_P1_DX: not a number ('1.2.3')"
    )
    _csv(path, [row(1000), row(2000)[:-1]])
    assert _error(path) == (
        f"{path}:3: 54 values, but the header has 55 columns"
    )
    _csv(path, [row(1000), ["", *row(0)[1:]]])
    assert _error(path) == (
        f"{path}:3: T_us: missing or not finite (sample 1)"
    )
    path.write_bytes(b"T_us,\xff\xfe\n")
    assert _one_line_error(path) == "not a CSV text file (byte 5 is not UTF-8)"
    path.write_text("# only a comment\n")
    assert _one_line_error(path) == "empty CSV (no header)"


def test_replay_cli_on_broken_files_prints_one_line_and_exits_1(tmp_path) -> None:
    """Through the installed command, as a user meets it: no traceback, the file and the part named."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    slipd = root / ".venv" / "bin" / "slipd"
    exe = [str(slipd)] if slipd.exists() else [str(root / ".venv" / "bin" / "python"), "-m", "slipd"]
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"PK\x03\x04 this is not a zip")  # raised zipfile.BadZipFile before
    back = tmp_path / "back.npz"
    rec = _rec(10)
    t = rec.t_us.copy()
    t[6] = 0
    _npz(back, t_us=t, force=rec.force, disp=rec.disp)
    for path, part in ((junk, "not an .npz recording (broken zip archive"), (back, "t_us: goes backwards at sample 6")):
        r = subprocess.run([*exe, "replay", str(path)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 1, r.stderr
        assert r.stdout == "" and r.stderr.count("\n") == 1, r.stderr
        assert r.stderr.startswith(f"slipd replay: {path}: {part}"), r.stderr


def test_the_controllers_friction_estimate_round_trips_and_replay_puts_it_beside_slipds(tmp_path) -> None:
    """An SDK log's S<s>_FrictionEst (the PapillArray controller's type-6 estimate; -1 where it has none)
    is kept as ``friction_est`` (NaN there), through npz and CSV, one and two sensors, and `slipd replay --json`
    reports it beside slipd's own estimate at each decision."""
    import json

    from slipd.cli import main

    rec = _rec(600)
    est = np.full(600, np.nan, np.float32)
    est[300:] = np.linspace(0.4, 0.6, 300)
    rec = Recording(rec.t_us, rec.force, rec.disp, rec.slip, rec.label, rec.object_motion, rec.meta, est)
    for path in (rec.save(tmp_path / "a.npz"), write_sdk_csv(rec, tmp_path / "a.csv")):
        back = Recording.load(path)
        np.testing.assert_array_equal(back.friction_est, est)  # NaN where none, bit for bit elsewhere (float32)
    text = (tmp_path / "a.csv").read_text().splitlines()
    col = text[1].split(",").index("S0_FrictionEst")
    assert float(text[2].split(",")[col]) == -1.0  # the SDK's "no estimate"
    two = Recording(rec.t_us, np.stack([rec.force] * 2, 1), np.stack([rec.disp] * 2, 1), meta={},
                    friction_est=np.stack([est, est * 2], 1))
    back = Recording.load(write_sdk_csv(two, tmp_path / "b.csv"))
    np.testing.assert_array_equal(back.friction_est, two.friction_est)
    assert back.sensor(1).friction_est is not None and np.nanmax(back.sensor(1).friction_est) == np.float32(1.2)
    with pytest.raises(RecordingError, match=r"friction_est: shape \(5,\), expected \[600\]"):
        Recording(rec.t_us, rec.force, rec.disp, friction_est=np.zeros(5))
    assert main(["replay", str(tmp_path / "a.npz"), "--json", str(tmp_path / "o.json")]) == 0
    decisions = json.loads((tmp_path / "o.json").read_text())["decisions"]
    assert decisions and all("friction" in d for d in decisions)
    for d in decisions:
        want = None if d["index"] < 300 else round(float(est[d["index"]]), 4)
        assert d["controller_friction"] == want


def test_replay_with_an_unknown_model_name_exits_4_with_one_line(capsys) -> None:
    """`--model` names a packaged model: an unknown name raised a traceback (exit 1) instead of the model's exit 4."""
    from slipd import models
    from slipd.cli import main

    code = main(["replay", str(models.SAMPLE_RECORDING), "--model", "nonexistent_model_name"])
    err = capsys.readouterr().err
    assert code == 4 and err.startswith("slipd replay:") and err.count("\n") == 1, err


def test_replay_sample_replays_the_packaged_recording_and_wants_it_or_a_file(tmp_path, capsys) -> None:
    """`slipd replay --sample` needs no path: the packaged sample slips and the shipped model alarms on it. A file and
    --sample together, or neither, is a usage error in one line."""
    from slipd import models
    from slipd.cli import main

    assert main(["replay", "--sample"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{models.SAMPLE_RECORDING}: 1500 samples") and "alarm at sample" in out, out
    assert "labelled onset at sample 1038" in out, out
    for argv in (["replay"], ["replay", "--sample", str(models.SAMPLE_RECORDING)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("slipd replay: give a RECORDING or --sample") and err.count("\n") == 1, err


def test_replay_on_metadata_the_decision_path_cannot_follow_prints_one_line(tmp_path, capsys) -> None:
    """A tare stretch beyond the recording, a tare stretch that is no [start, stop], a tare offset of the wrong shape,
    a --json into a folder that does not exist: each raised a traceback (the last after the output was printed)."""
    from slipd.cli import main

    cases = {"short.npz": (_rec(10), {"tare_samples": [20, 300]}, "[20, 300] is not a stretch of its 10 samples"),
             "long.npz": (_rec(200), {"tare_samples": [20, 5000]}, "[20, 5000] is not a stretch of its 200 samples"),
             "neg.npz": (_rec(200), {"tare_samples": [-30, -1]}, "[-30, -1] is not a stretch of its 200 samples"),
             "stretch.npz": (_rec(200), {"tare_samples": 5}, "meta tare_samples: 5, expected [start, stop]"),
             "offset.npz": (_rec(200), {"tare_offset": [1, 2, 3]}, "meta tare_offset: shape [3], expected [9, 3]")}
    for name, (rec, meta, part) in cases.items():
        rec.meta.update(meta)
        rec.save(tmp_path / name)
        assert main(["replay", str(tmp_path / name)]) == 1
        out = capsys.readouterr()
        assert out.out == "" and out.err.count("\n") == 1 and part in out.err, out.err
    rec = _rec(200)
    rec.save(tmp_path / "ok.npz")
    assert main(["replay", str(tmp_path / "ok.npz"), "--json", str(tmp_path / "nowhere" / "o.json")]) == 2
    out = capsys.readouterr()
    assert out.out == "" and "its folder does not exist" in out.err


def test_replay_refuses_what_the_daemon_would_not_decide_on_alike(tmp_path, capsys) -> None:
    """A recording at another rate than the model's (by its timestamps or its meta), a two-sensor CSV missing some of a
    finger's columns, a --json path that is a folder: one line each, where replay decided on them and exited 0 (a
    100 Hz log went through the 1 kHz model and missed its slip; the finger with missing columns was dropped)."""
    from slipd.cli import main
    from slipd.models import SAMPLE_RECORDING

    sample = Recording.load(SAMPLE_RECORDING)
    slow = Recording.load(SAMPLE_RECORDING)
    slow.t_us = slow.t_us * 10
    slow.save(tmp_path / "r100.npz")
    stated = Recording.load(SAMPLE_RECORDING)
    stated.meta["rate_hz"] = 500
    stated.save(tmp_path / "meta500.npz")
    two = Recording(t_us=sample.t_us, force=np.stack([sample.force] * 2, 1), disp=np.stack([sample.disp] * 2, 1))
    write_sdk_csv(two, tmp_path / "two.csv")
    lines = (tmp_path / "two.csv").read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, h in enumerate(header) if not (h.startswith("S1_") and "_D" in h)]
    (tmp_path / "partial.csv").write_text("\n".join(",".join(r.split(",")[i] for i in keep) for r in lines) + "\n")
    cases = {"r100.npz": "sampled at 100.0 Hz by its timestamps", "meta500.npz": "sampled at 500 Hz by meta rate_hz",
             "partial.csv": "sensor S1 has 27 of its 54 columns"}
    for name, part in cases.items():
        assert main(["replay", str(tmp_path / name)]) == 1
        out = capsys.readouterr()
        assert out.out == "" and out.err.count("\n") == 1 and part in out.err, out.err
    assert main(["replay", str(SAMPLE_RECORDING), "--json", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    bom = tmp_path / "bom.csv"  # a spreadsheet's re-save puts a byte order mark before the header
    write_sdk_csv(sample, tmp_path / "plain.csv")
    bom.write_text("\ufeff" + (tmp_path / "plain.csv").read_text(), encoding="utf-8")
    assert np.array_equal(read_sdk_csv(bom).force, read_sdk_csv(tmp_path / "plain.csv").force)


def test_replay_says_where_the_daemon_would_go_blind_on_non_finite_samples(tmp_path, capsys) -> None:
    """Non-finite samples are held over by the features in replay, but the daemon fails safe once a run of them
    outlasts its bridge (5 ms): replay says so (printed and in the JSON), and a recording with no finite sample at all
    exits 1 (it printed a clean 'no alarm')."""
    import json

    from slipd.cli import main
    from slipd.models import SAMPLE_RECORDING

    rec = Recording.load(SAMPLE_RECORDING)
    rec.force[1000:] = np.inf
    rec.save(tmp_path / "inf.npz")
    assert main(["replay", str(tmp_path / "inf.npz"), "--json", str(tmp_path / "o.json")]) == 0
    t0 = int(rec.t_us[0])
    assert f"fail safe (sensor_nonfinite) at t={(int(rec.t_us[1005]) - t0) / 1e6:.3f} s" in capsys.readouterr().out
    out = json.loads((tmp_path / "o.json").read_text())
    assert out["nonfinite_samples"] == len(rec) - 1000 and out["failsafe_t_us"] == int(rec.t_us[1005])
    rec.force[:] = np.nan
    rec.save(tmp_path / "nan.npz")
    assert main(["replay", str(tmp_path / "nan.npz")]) == 1
    assert "no finite sample" in capsys.readouterr().err


def test_the_rate_of_a_recording_with_repeated_timestamps_is_the_sensors() -> None:
    """Timestamps that repeat are accepted (they do not go backwards); the median spacing was then 0 and the rate a
    ZeroDivisionError."""
    rec = _rec(10)
    rec.t_us[:] = 5000
    assert rec.rate_hz == 1000.0


def test_replay_says_when_the_recording_was_decided_by_another_model(tmp_path, capsys) -> None:
    """The daemon's recordings carry the sha256 of the model that decided them; a replay with another model printed
    its decisions as if they were the robot's. Now it says so (printed and in the JSON); the same model: nothing."""
    import json

    from slipd import models
    from slipd.cli import main
    from slipd.detect.manifest import read_manifest

    shipped = read_manifest(models.packaged(models.DEFAULT_MODEL)).sha256
    for name, sha in (("other.npz", "0" * 64), ("same.npz", shipped)):
        rec = Recording.load(models.SAMPLE_RECORDING)
        rec.meta["model_sha256"] = sha
        rec.save(tmp_path / name)
        assert main(["replay", str(tmp_path / name), "--json", str(tmp_path / "o.json")]) == 0
        said = "recorded with model sha256 0000000000000000" in capsys.readouterr().out
        assert said == (sha != shipped)
        out = json.loads((tmp_path / "o.json").read_text())
        assert out["recorded_model_sha256"] == sha and out["model_sha256"] == shipped
