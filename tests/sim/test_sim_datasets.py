"""Data sets: determinism, disjoint seeds, the transfer design, the make_dataset and realism tools."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slipd.recording import Recording
from slipd.sim.datasets import dataset_scenes, one_coefficient, scene_seed, transfer_design, write_dataset
from sliplab import make_dataset, realism


def test_train_and_test_never_share_a_seed():
    train = {scene_seed(s, "train", seed, i) for s in ("offline", "transfer") for seed in (0, 1, 999)
             for i in (0, 1, 99_999)}
    test = {scene_seed(s, "test", seed, i) for s in ("offline", "transfer") for seed in (0, 1, 999)
            for i in (0, 1, 99_999)}
    assert not train & test
    with pytest.raises(ValueError):
        scene_seed("offline", "valid", 0, 0)
    a = dataset_scenes("offline", "train", 5, 0)
    b = dataset_scenes("offline", "test", 5, 0)
    assert [d for d, _ in a] != [d for d, _ in b]


def test_transfer_design_is_the_216_trial_design():
    design = transfer_design()
    assert len(design) == 216
    assert sum(d["trial"] == "stop" for d in design) == 54
    assert {d["object"]["name"] for d in design} == {
        "hard_paper_box", "wooden_box", "shampoo_bottle", "coffee_jar", "pringles_can", "thermos_flask"}
    assert {d["motion"]["level"] for d in design} == {"low", "medium", "high"}
    assert all(d["sensor"] == "v2" for d in design)


def test_make_dataset_writes_deterministic_recordings(tmp_path, capsys):
    out1, out2 = tmp_path / "a", tmp_path / "b"
    assert make_dataset.main(["--set", "offline", "--split", "test", "--out", str(out1), "--count", "4"]) == 0
    printed = capsys.readouterr().out
    assert "x real time" in printed
    write_dataset("offline", "test", out2, count=4)
    index = json.loads((out1 / "index.json").read_text())
    assert index["count"] == 4 and len(index["recordings"]) == 4
    for entry in index["recordings"]:
        r1, r2 = Recording.load(out1 / entry["file"]), Recording.load(out2 / entry["file"])
        assert np.array_equal(r1.force, r2.force) and np.array_equal(r1.label, r2.label)
        assert r1.meta["sensor"]["name"] == "v1" and entry["scene"]["family"] == "hexapod"
        assert entry["label_samples"] == int(r1.label.sum())


def test_realism_skips_cleanly_without_checkpoints(tmp_path, capsys):
    assert realism.main(["--count", "2", "--ckpt", str(tmp_path)]) == 0
    assert "skipping" in capsys.readouterr().out


def test_realism_runs_the_reference_ensemble(reference_ckpt_dir, capsys):
    assert realism.main(["--count", "6", "--ckpt", str(reference_ckpt_dir)]) == 0
    out = capsys.readouterr().out
    assert "slip scenes detected" in out and "first alarm - onset" in out


@pytest.fixture(scope="module")
def robust_folder(tmp_path_factory):
    """Five robust test recordings: one per physics family."""
    out = tmp_path_factory.mktemp("robust")
    write_dataset("robust", "test", out, count=5)
    return out


def test_realism_scores_recordings_per_physics_family(robust_folder):
    from sliplab.robustness import tags

    paths = sorted(robust_folder.glob("*.npz"))
    recs = [Recording.load(p) for p in paths]
    fams = [tags(robust_folder)[p.stem]["physics_family"] for p in paths]
    ends = [np.arange(39, len(r), 40) for r in recs]
    quiet = realism.evaluate_recordings(recs, [p.stem for p in paths], fams, [np.zeros(len(e)) for e in ends], ends)
    assert set(quiet) == set(fams) | {"all"} and list(quiet)[-1] == "all"
    a = quiet["all"]
    assert a["detected"] == 0 and a["quiet"] == a["no_slip"] and a["slip"] + a["unscored"] + a["no_slip"] == 5
    assert a["missed"] == a["slip"]
    loud = realism.evaluate_recordings(recs, [p.stem for p in paths], fams, [np.ones(len(e)) for e in ends], ends)
    assert loud["all"]["quiet"] == 0 and loud["all"]["early"] == loud["all"]["slip"]  # an alarm at 0.04 s


def test_realism_runs_on_recordings(robust_folder, reference_ckpt_dir, capsys):
    assert realism.main(["--recordings", str(robust_folder), "--limit", "5", "--ckpt", str(reference_ckpt_dir)]) == 0
    out = capsys.readouterr().out
    assert "5 of 5 recordings" in out and "physics family" in out and "stick_slip" in out


def test_every_stop_trial_of_the_transfer_design_holds_its_object():
    """A stop trial is labelled no-slip throughout, so its secure grip must hold: no gross motion (2 mm / 2 deg) at
    the fastest lift. Off-centre lifts are the hard case (generator slipd.sim/2 put the centre of mass 15 mm out,
    where no grip up to 60 N holds any object, and every off-centre stop trial turned ~80 deg)."""
    from slipd.sim.scene import GROSS_DEG, GROSS_MM, generate_batch, parse_scene

    stops = [d for d in transfer_design() if d["trial"] == "stop" and d["motion"]["level"] == "high"]
    recs = generate_batch([parse_scene(d) for d in stops], [0] * len(stops))
    for d, r in zip(stops, recs, strict=True):
        mot = r.object_motion - r.object_motion[0]
        assert np.hypot(mot[:, 0], mot[:, 1]).max() < GROSS_MM and np.abs(mot[:, 2]).max() < GROSS_DEG, d["name"]


def test_the_twists_set_is_off_centre_slip_trials_beyond_any_secure_grip():
    from slipd.sim.datasets import TWIST_OFFSET_MM, gripper_scene

    scenes = [d for d, _ in dataset_scenes("twists", "train", 20, 0)]
    assert all(d["trial"] == "slip" and d["_tags"]["scenario"] == "twist" for d in scenes)
    offsets = [d["object"]["com_offset_mm"][0] for d in scenes]
    assert all(TWIST_OFFSET_MM[0] <= x <= TWIST_OFFSET_MM[1] for x in offsets) and len(set(offsets)) == 20
    with pytest.raises(ValueError, match="stop trial"):
        gripper_scene("coffee_jar", "lift_offcentre", "high", None, offcentre_mm=15.0)


def test_the_lights_set_grips_at_a_few_newtons_and_its_stop_trials_hold():
    from slipd.sim.datasets import LIGHT_HOLD_N
    from slipd.sim.scene import GROSS_DEG, GROSS_MM, generate_batch, parse_scene

    scenes = [d for d, _ in dataset_scenes("lights", "train", 40, 0)]
    assert all(d["family"] == "gripper" and d["_tags"]["scenario"] == "light" for d in scenes)
    slips = [d for d in scenes if d["trial"] == "slip"]
    stops = [d for d in scenes if d["trial"] == "stop"]
    assert slips and stops
    # Every slip trial grips below what holds its object, and at most at the top of LIGHT_HOLD_N.
    assert all(0.3 < d["grip"]["force_n"] < LIGHT_HOLD_N[1] for d in slips)
    assert not any(d["motion"]["kind"] == "lift" and d["object"]["com_offset_mm"][0] for d in stops)
    # A stop trial is labelled no-slip throughout, so its secure grip must hold the light object at the fastest lift.
    held = [d for d in stops if d["motion"]["kind"] == "lift"][:3]
    fast = [{**d, "motion": {**d["motion"], "level": "high"}, "settle_s": 0.2} for d in held]
    fast = [{k: v for k, v in d.items() if k not in ("_tags", "duration_s")} for d in fast]
    recs = generate_batch([parse_scene(d) for d in fast], [0] * len(fast))
    for d, r in zip(fast, recs, strict=True):
        mot = r.object_motion - r.object_motion[0]
        assert np.hypot(mot[:, 0], mot[:, 1]).max() < GROSS_MM and np.abs(mot[:, 2]).max() < GROSS_DEG, d["name"]
        assert not r.label.any(), d["name"]


def test_the_coulomb_set_has_one_friction_coefficient_and_slips_without_a_force_drop():
    from slipd.sim import generate, parse_scene

    scenes = dataset_scenes("coulomb", "test", 6, 0)
    assert [d["family"] for d, _ in scenes] == ["hexapod", "gripper"] * 3
    for d, _ in scenes:
        fr = d["friction"] if d["family"] == "hexapod" else d["object"]
        assert fr["mu_k"] == fr["mu_s"]
    # The same slip with the other sets' kinetic coefficient drops the sliding pillar's utilisation after it breaks
    # away; with one coefficient it stays at mu_s.
    grip = next(d for d, _ in dataset_scenes("grips", "test", 40, 0) if d["trial"] == "slip")
    peaks = {}
    for name, d in (("drop", grip), ("coulomb", one_coefficient(grip))):
        rec = generate(parse_scene({k: v for k, v in d.items() if k != "_tags"}), seed=3)
        assert rec.slip is not None and rec.slip.any()
        f = rec.force
        util = np.hypot(f[..., 0], f[..., 1]) / np.maximum(f[..., 2], 0.5)
        p = int(np.argmax(rec.slip.any(0) * f[int(np.argmax(rec.slip.any(1))), :, 2]))  # the most loaded slider
        start = int(np.argmax(rec.slip[:, p]))
        peaks[name] = (util[: start + 1, p].max(), np.median(util[start + 20: start + 120, p]))
    mu_s, mu_k = grip["object"]["mu_s"], grip["object"]["mu_k"]
    assert peaks["drop"][1] < peaks["drop"][0] * (mu_k / mu_s + 1) / 2
    assert peaks["coulomb"][1] > peaks["coulomb"][0] * 0.97
