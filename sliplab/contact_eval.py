"""Score the contact state (``slipd.detect.contact``) against the simulator's truth.

    python tools/evaluate.py --contact [--sets robust,transfer,offline] [--split test] [--json OUT]

Every recording streams through ``ContactStream`` (the daemon's code, with the shipped model's feature layout:
window 40, stride 10, median 5, as the daemon's detector shares its filtered window) with the offset of its
unloaded start. Two figures:

* **per-pillar slip**: at every window end, each pillar in contact (filtered Fz > 0.5 N) is one case,
  predicted slipping when P(slip) >= 0.5, truth the simulator's per-pillar ``slip``; precision, recall
  and F1 pooled over all cases, per pillar, per set, per physics family and per phase of the scene's
  timeline (press, hold, move, release; 'other': the unloaded start and scenes without a timeline, the
  gripper's) -- which says where the estimate loses its precision;
* **friction**: on every slip trial, the estimate 0.2 s after the truth's gross-slip time (all considered
  pillars slipping; the onset + 0.5 s where there is none) against the truth: the scene's kinetic
  coefficient ``mu_k`` (a sliding tip's |Ft| / Fz), and where the scene has per-pillar friction spread,
  ``mu_k`` times the normal-force-weighted mean of the spread factors of the pillars sliding then (the
  Stribeck family's mu(v) lies between mu_k and mu_s: it is scored against mu_k all the same). A trial
  counts as within when |estimate - truth| <= 15 % of the truth; a trial with no estimate by then counts
  as outside. Where a recording carries the PapillArray controller's own
  type-6 friction estimate (``Recording.friction_est``: an SDK log's ``S0_FrictionEst``), it is scored the same way
  at the same sample; the simulated sets carry none.
* **silent stops**: every end of a pillar's slide in the truth (sliding for at least 0.1 s, then stuck for at least
  0.5 s, in contact) that no pillar's forces show: every pillar's mean |Ft| and Fz over 0.2-0.5 s after the stop
  within 2 % (and 0.01 N) of their means over the 0.1 s before, and their standard deviations within 25 % (and
  0.002 N) of theirs. Until some force moves, the sensor reads what it
  read during the slide, so no estimate from the forces can tell that pillar from one sliding steadily; the cases
  scored there (truth: stuck) are counted apart, with how many of them the estimate called sliding.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from slipd.detect.build import build_detector
from slipd.detect.contact import ContactStream
from slipd.detect.ensemble import Ensemble
from slipd.detect.features import stretch_offset
from slipd.detect.manifest import load_manifest
from slipd.models import DEFAULT_MODEL, packaged
from slipd.recording import Recording
from sliplab.paths import ROOT

SPEC = load_manifest(packaged(DEFAULT_MODEL), check_graph=False).spec
"""The shipped model's feature layout: its window, stride and median are what the daemon's contact state sees (the
detector shares its filtered window with the contact stream, ``ContactStream.shares_window``)."""
TOLERANCE = 0.15
SLIDE_S, STUCK_S = 0.1, 0.5
"""A stop counts when the pillar slid this long before it and stays stuck this long after it."""
SILENT_SHARE, SILENT_FLOOR_N = 0.02, 0.01
"""Forces within this share of their value (plus this floor: sensor noise) across a stop leave it silent."""
SILENT_SD_SHARE, SILENT_SD_FLOOR_N = 0.25, 0.002
"""... and their standard deviations within this share (plus this floor)."""
SETTLE_S = 0.2
"""The forces after a stop are compared from this long after it (the tip's own settling) to ``STUCK_S``."""
MEAN_N = 20
"""Samples of the running mean that says when a silent stop's forces move at last."""


def truth_friction(meta: dict[str, Any]) -> tuple[float, float] | None:
    """(mu_s, mu_k) of a recording's scene (hexapod ``friction`` or gripper ``object``), or None."""
    scene = meta.get("scene", meta)
    src = scene.get("friction") or scene.get("object")
    if not src or "mu_k" not in src:
        return None
    return float(src["mu_s"]), float(src["mu_k"])


_MODEL: dict[str, Any] = {}


def _states(rec: Recording, model: str | None, offset: np.ndarray) -> Any:
    """(window end, ContactState, filtered normal forces [9]) of every decision, tared with ``offset`` (that of
    the recording's unloaded start): ``ContactStream`` alone (the feature estimate), or with ``model`` the daemon's
    detector, whose contact state takes the model's own per-pillar P(slip) where its graph has a per-pillar head
    (``slipd.detect.contact``)."""
    if model is None:
        stream = ContactStream(SPEC, offset)
        for j, st in stream.push_many(rec.force):
            yield j, st, _fz(stream)
        return
    ens = _MODEL.get(model)
    if ens is None:
        ens = _MODEL[model] = Ensemble.load(model)
    ens.reset()
    det = build_detector(None, ens, offset=offset)
    for j, d in det.push_many(rec.force, rec.t_us):
        if d.contact is not None:
            yield j, d.contact, rec.force[j, :, 2] - offset[:, 2]  # the tared normal forces at the window's end


def phase_bounds(meta: dict[str, Any]) -> list[tuple[float, float, str]]:
    """(start s, end s, op) of each segment of a scene's timeline (after its unloaded ``pre_s``); [] without one."""
    scene = meta.get("scene")
    if not isinstance(scene, dict) or not scene.get("timeline"):
        return []
    out, t = [], float(scene.get("pre_s", 0.0))
    for seg in scene["timeline"]:
        out.append((t, t + float(seg["duration_s"]), str(seg["op"])))
        t += float(seg["duration_s"])
    return out


def silent_stops(force: np.ndarray, slip: np.ndarray, rate_hz: float) -> tuple[int, int, np.ndarray]:
    """(stops, silent stops, mask [N, 9]) of a tared recording's slide ends (see the module's text): ``mask`` marks
    each silent stop's stuck samples until some pillar's forces (a 20-sample mean) leave the band around their
    values during the slide."""
    n = len(force)
    slide, stuck, settle = round(SLIDE_S * rate_hz), round(STUCK_S * rate_hz), round(SETTLE_S * rate_hz)
    ft = np.hypot(force[:, :, 0], force[:, :, 1])
    fz = force[:, :, 2]
    k = MEAN_N
    csum_t = np.concatenate([np.zeros((1, 9)), np.cumsum(ft, axis=0)])
    csum_z = np.concatenate([np.zeros((1, 9)), np.cumsum(fz, axis=0)])
    mask = np.zeros((n, 9), bool)
    stops = silent = 0
    for p in range(9):
        s = slip[:, p].astype(np.int8)
        ends = np.flatnonzero((s[:-1] == 1) & (s[1:] == 0)) + 1
        for i in ends:
            if i < slide or not s[i - slide : i].all():
                continue
            next_slip = np.flatnonzero(s[i:])
            run_end = i + (int(next_slip[0]) if len(next_slip) else n - i)
            if run_end - i < stuck:
                continue
            if fz[i - slide : i, p].mean() <= 0.5:
                continue
            stops += 1
            # Every pillar's forces, not only this one's: a stop that any pillar shows (one still stuck stops
            # loading) is information a model could use.
            before, after = slice(i - slide, i), slice(i + settle, i + stuck)
            t_b, z_b = ft[before].mean(0), fz[before].mean(0)
            t_a, z_a = ft[after].mean(0), fz[after].mean(0)
            tol_t, tol_z = SILENT_SHARE * np.abs(t_b) + SILENT_FLOOR_N, SILENT_SHARE * np.abs(z_b) + SILENT_FLOOR_N
            if (np.abs(t_a - t_b) > tol_t).any() or (np.abs(z_a - z_b) > tol_z).any():
                continue
            # Nor a change in how the forces fluctuate (a stick-slip slide's chatter stopping).
            sd_b = np.concatenate([ft[before].std(0), fz[before].std(0)])
            sd_a = np.concatenate([ft[after].std(0), fz[after].std(0)])
            if (np.abs(sd_a - sd_b) > SILENT_SD_SHARE * sd_b + SILENT_SD_FLOOR_N).any():
                continue
            silent += 1
            j = np.arange(i + k, run_end)
            mt = (csum_t[j] - csum_t[j - k]) / k
            mz = (csum_z[j] - csum_z[j - k]) / k
            moved = np.flatnonzero(((np.abs(mt - t_b) > tol_t) | (np.abs(mz - z_b) > tol_z)).any(axis=1))
            mask[i : int(j[moved[0]]) if len(moved) else run_end, p] = True
    return stops, silent, mask


def score_recording(path: str, model: str | None = None) -> dict[str, Any]:
    """Stream one recording; per-pillar counts (per pillar and per timeline phase) and the friction estimate at
    gross slip."""
    rec = Recording.load(path)
    meta = rec.meta
    counts = np.zeros((9, 3), np.int64)  # tp, fp, fn per pillar
    bounds = phase_bounds(meta)
    phases: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(3, np.int64))
    ev = rec.events
    at = ev["gross_slip"] + 0.2 if "gross_slip" in ev else (ev["onset"] + 0.5 if "onset" in ev else None)
    at_i = None if at is None else min(int(at * rec.rate_hz), len(rec) - 1)
    est = None
    stops = silent = 0
    hidden = np.zeros(2, np.int64)  # cases stuck at a slide's forces after a silent stop, and those called sliding
    offset = stretch_offset(rec.force, meta.get("tare_samples", (0, 100)))
    if rec.slip is not None:
        stops, silent, quiet = silent_stops(rec.force - offset, rec.slip, rec.rate_hz)
    for j, st, fz in _states(rec, model, offset):
        if rec.slip is not None:
            c = np.asarray(st.pillar_slip) >= 0.5
            fz_ok = fz > 0.5
            pred, tr = c & fz_ok, rec.slip[j] & fz_ok
            case = np.stack([pred & tr, pred & ~tr, ~pred & tr], axis=1)  # tp, fp, fn per pillar
            counts += case
            in_quiet = quiet[j] & fz_ok & ~tr
            hidden += (int(in_quiet.sum()), int((in_quiet & pred).sum()))
            t = j / rec.rate_hz
            phases[next((op for a, b, op in bounds if a <= t < b), "other")] += case.sum(0)
        if at_i is not None and j <= at_i:
            est = st.friction
    truth = truth_friction(meta)
    if truth is not None and at_i is not None and isinstance(meta.get("physics"), dict) and "spread" in meta["physics"]:
        from slipd.sim.contact_models import build_model, pillar_spread

        mult = pillar_spread(build_model(meta["physics"]), int(meta["seed"]))["mu"]
        sliding = rec.slip[at_i] if rec.slip is not None and rec.slip[at_i].any() else np.ones(9, bool)
        w = np.maximum(rec.force[at_i, :, 2], 0.0) * sliding
        if w.sum() > 0:
            truth = (truth[0], truth[1] * float(np.dot(w, mult) / w.sum()))
    return {"file": Path(path).name, "family": meta.get("physics_family", meta.get("scene", {}).get("family", "?")),
            "kind": meta.get("kind"), "counts": counts.tolist(), "friction": est,
            "phases": {k: v.tolist() for k, v in phases.items()},
            "mu_s": None if truth is None else truth[0], "mu_k": None if truth is None else truth[1],
            "controller_friction": _controller_friction(rec, at_i),
            "stops": stops, "silent_stops": silent, "silent_cases": hidden.tolist()}


def _controller_friction(rec: Recording, at: int | None) -> float | None:
    """The PapillArray controller's own estimate (its type-6 block, the SDK log's ``S0_FrictionEst``) of sensor 0 at
    sample ``at``, where the recording has one."""
    if rec.friction_est is None or at is None:
        return None
    v = float(np.ravel(rec.friction_est[at])[0])
    return v if np.isfinite(v) else None


def _fz(stream: ContactStream) -> np.ndarray:
    # The last filtered sample's normal forces: the stream keeps them in its feature history.
    f = stream.features
    return f._buf[f._end - 1].reshape(9, 3)[:, 2]


def _close(estimate: float, truth: float) -> bool:
    """An estimate within ``TOLERANCE`` of the truth."""
    return abs(estimate - truth) <= TOLERANCE * truth


def _within(pairs: list[tuple[float, float]]) -> float | None:
    """Share of (estimate, truth) pairs within ``TOLERANCE`` of the truth (None without pairs)."""
    return float(np.mean([_close(e, t) for e, t in pairs])) if pairs else None


def prf(tp: int, fp: int, fn: int) -> tuple[float, float, float]:
    """Precision, recall, F1 (0 where undefined)."""
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    return p, r, (2 * p * r / (p + r) if p + r else 0.0)


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Pooled and per-pillar F1, per-family friction accuracy."""
    total = np.sum([r["counts"] for r in rows], axis=0)
    per_pillar = [prf(*map(int, total[p]))[2] for p in range(9)]
    pooled = prf(*map(int, total.sum(0)))
    fam: dict[str, list[bool]] = defaultdict(list)
    errs: dict[str, list[float]] = defaultdict(list)
    for r in rows:
        if r["kind"] != "slip" or r["mu_k"] is None:
            continue
        ok = r["friction"] is not None and _close(r["friction"], r["mu_k"])
        fam[r["family"]].append(bool(ok))
        if r["friction"] is not None:
            errs[r["family"]].append((r["friction"] - r["mu_k"]) / r["mu_k"])
    within = [v for vs in fam.values() for v in vs]
    by_phase: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(3, np.int64))
    for r in rows:
        for ph, c in r.get("phases", {}).items():
            by_phase[ph] += c
    phase = {ph: dict(zip(("precision", "recall", "f1"), prf(*map(int, c)), strict=True))
             | {"tp": int(c[0]), "fp": int(c[1]), "fn": int(c[2])} for ph, c in sorted(by_phase.items())}
    by_family: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(3, np.int64))
    for r in rows:
        by_family[str(r["family"])] += np.asarray(r["counts"]).sum(0)
    family = {f: dict(zip(("precision", "recall", "f1"), prf(*map(int, c)), strict=True))
              for f, c in sorted(by_family.items())}
    return {
        "pillar": {"precision": pooled[0], "recall": pooled[1], "f1": pooled[2], "f1_per_pillar": per_pillar,
                   "per_phase": phase, "per_family": family},
        "friction": {"trials": len(within), "within_15pct": float(np.mean(within)) if within else 0.0,
                     "per_family": {f: {"trials": len(v), "within_15pct": float(np.mean(v)),
                                        "median_rel_error": float(np.median(errs[f])) if errs[f] else None}
                                    for f, v in sorted(fam.items())}},
        "silent_stops": _silent(rows),
        "controller_friction_recordings": sum(r["controller_friction"] is not None for r in rows),
        "controller_friction_within_15pct": _within([(r["controller_friction"], r["mu_k"]) for r in rows
                                                     if r["controller_friction"] is not None and r["mu_k"]]),
    }


def _silent(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Silent stops pooled and per family, with the negative cases they leave and the estimate's false positives
    among them (all against the pooled false positives)."""
    def pool(rs: list[dict[str, Any]]) -> dict[str, int]:
        cases = np.sum([r["silent_cases"] for r in rs], axis=0) if rs else np.zeros(2, np.int64)
        return {"stops": sum(r["stops"] for r in rs), "silent": sum(r["silent_stops"] for r in rs),
                "cases": int(cases[0]), "called_sliding": int(cases[1]),
                "false_positives": int(np.sum([np.asarray(r["counts"])[:, 1].sum() for r in rs]))}
    fams: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        fams[str(r["family"])].append(r)
    return pool(rows) | {"per_family": {f: pool(rs) for f, rs in sorted(fams.items())}}


def main(argv: list[str] | None = None) -> int:
    """Score the sets and print the figures."""
    p = argparse.ArgumentParser(description="score per-pillar slip and the friction estimate against truth")
    p.add_argument("--sets", default="robust,transfer,offline")
    p.add_argument("--split", default="test")
    p.add_argument("--data-root", default=str(ROOT / "out" / "datasets"))
    p.add_argument("--count", type=int, default=None, help="first N recordings of each set")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--json", help="write the figures here")
    p.add_argument("--model", help="score the detector of this manifest (its per-pillar head where it has one) "
                                   "instead of the feature pipeline's estimate alone")
    args = p.parse_args(argv)
    out: dict[str, Any] = {}
    all_rows: list[dict[str, Any]] = []
    for name in args.sets.split(","):
        folder = Path(args.data_root) / f"{name}_{args.split}"
        files = sorted(str(f) for f in folder.glob("*.npz"))[: args.count]
        if not files:
            print(f"{folder}: no recordings (python tools/make_dataset.py --set {name} --split {args.split})")
            continue
        with ProcessPoolExecutor(args.workers) as pool:
            rows = list(pool.map(score_recording, files, [args.model] * len(files), chunksize=4))
        all_rows += rows
        out[name] = summarise(rows)
        _print(f"{name}_{args.split} ({len(rows)} recordings)", out[name])
    if all_rows:
        out["all"] = summarise(all_rows)
        _print(f"all sets ({len(all_rows)} recordings)", out["all"])
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


def _print(title: str, s: dict[str, Any]) -> None:
    pl, fr = s["pillar"], s["friction"]
    print(f"{title}: per-pillar slip P {pl['precision']:.3f} R {pl['recall']:.3f} F1 {pl['f1']:.3f} "
          f"(per pillar {' '.join(f'{f:.2f}' for f in pl['f1_per_pillar'])})")
    print("  per family: " + ", ".join(f"{f} P {v['precision']:.2f} R {v['recall']:.2f} F1 {v['f1']:.2f}"
                                      for f, v in pl["per_family"].items()))
    print("  per phase: " + ", ".join(f"{ph} P {v['precision']:.2f} R {v['recall']:.2f} (fp {v['fp']}, fn {v['fn']})"
                                     for ph, v in pl["per_phase"].items()))
    print(f"  friction within 15 % of mu_k on {fr['within_15pct']:.1%} of {fr['trials']} slip trials; " + ", ".join(
        f"{f} {v['within_15pct']:.0%} of {v['trials']} (median error {v['median_rel_error']:+.1%})"
        if v["median_rel_error"] is not None else f"{f} {v['within_15pct']:.0%} of {v['trials']}"
        for f, v in fr["per_family"].items()))
    sl = s["silent_stops"]
    print(f"  slide ends (>= {SLIDE_S:g} s sliding, >= {STUCK_S:g} s stuck): {sl['stops']}, silent (forces within "
          f"{SILENT_SHARE:.0%}, spread within {SILENT_SD_SHARE:.0%}): {sl['silent']}; "
          f"stuck cases at a slide's forces {sl['cases']}, called sliding "
          f"{sl['called_sliding']} of the {sl['false_positives']} false positives; per family " + ", ".join(
              f"{f} {v['silent']}/{v['stops']}" for f, v in sl["per_family"].items()))
    ctl = s["controller_friction_within_15pct"]
    print(f"  recordings with the controller's type-6 friction estimate: {s['controller_friction_recordings']}"
          + ("" if ctl is None else f"; its estimate within 15 % of mu_k on {ctl:.1%} of them"))
