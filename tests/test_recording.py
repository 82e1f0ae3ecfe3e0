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
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match=r"junk\.npz"):
        Recording.load(junk)
    with pytest.raises(RecordingError, match="force/disp"):
        Recording(t_us=np.arange(3), force=np.zeros((3, 8, 3)), disp=np.zeros((3, 9, 3)))
