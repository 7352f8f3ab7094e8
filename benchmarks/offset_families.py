"""Issue #19 item 4 / #24: the pose/range clock offset's convergence, its sd and the stretches' Q test.

    python benchmarks/offset_families.py --seeds 1-19:2 [--drift 0 0.02] [--stated-drift] [--jump 0 0.15]
    python benchmarks/offset_families.py --real [--starts 0 -0.1] [--options freeze_scale=false]
    python benchmarks/offset_families.py --summary LOG

The estimator alone (`nls.prepare_offset`'s steps: `nls` at the stated offset on a subsample, then
`offset.estimate`), timed (`estimate` only; `seconds_first` includes compilation, `seconds` a second warm
call on real recordings). Simulated: scenario `small`, offset uniform in +-0.3 s per seed (as
`gp_families.py --offset rand`), odometry drift (`--drift`, stated as `pose_drift` with `--stated-drift`,
which also prints the unstated row from the same start fit), and `--jump J`: the ranges of the second half
of the campaign carry an offset J s larger (the clock jumped; the Q test should make the offset NaN).
Real: the shared recordings of `uncertainty_trajectory.real_datasets`, from each start in `--starts`. One
JSON line per run: estimate, sd, rounds, converged, the Q test's p-value and the stretches' offsets, reason,
seconds. With PYTHONPATH pointing at an older checkout whose `estimate` takes no options, leave `--options`
out: the fields it lacks are null (the before/after timing of the docs).
"""

from __future__ import annotations

import argparse
import json
import time

import equinox as eqx
import numpy as np

from jaxcal.precision import in_float64
from jaxcal.trajectory import nls
from jaxcal.trajectory.poses import estimate_offset_fit, fit_poses, prepare


def parse_seeds(text: str) -> list[int]:
    rng, _, step = text.partition(":")
    lo, _, hi = rng.partition("-")
    return list(range(int(lo), int(hi or lo) + 1, int(step or 1)))


def run(ds, start_s: float, drift: float, options: dict, repeat: bool, also_unstated: bool = False) -> list[dict]:
    p = nls.NLSParams(time_offset_s=start_s)
    g, _ = prepare(ds, p.order, p.knot_dt_s, p.max_gap_s, start_s, max_per_anchor=nls.START_PER_ANCHOR)
    (est, _, bias, _), _, _ = nls.solve_all_checked(g, p)
    model = fit_poses(ds, p.order, p.knot_dt_s, p.max_gap_s)
    outs = []
    for d in ([0.0] if also_unstated and drift > 0 else []) + [drift]:
        opts = dict(options)
        if d > 0:
            opts.update(pose_drift=d, pose_t0=float(np.asarray(ds.pose_time)[0]))
        outs.append(_estimate(model, ds, est, bias, start_s, p.max_offset_s, opts, repeat))
    return outs


def _estimate(model, ds, est, bias, start_s, max_offset_s, opts, repeat) -> dict:
    def once():
        t = time.perf_counter()
        fit = estimate_offset_fit(model, ds, np.asarray(est), np.asarray(bias), start_s, max_offset_s, **opts)
        return fit, time.perf_counter() - t

    fit, sec = once()
    first = sec
    if repeat:
        fit, sec = once()
    return {
        "offset_s": fit.offset_s,
        "sd_s": fit.sd_s,
        "rounds": getattr(fit, "rounds", None),
        "converged": getattr(fit, "converged", None),
        "stretch_p": getattr(fit, "stretch_p", None),
        "stretch_offsets_s": list(getattr(fit, "stretch_offsets_s", ())),
        "pose_sd_s": getattr(fit, "pose_sd_s", None),
        "reason": fit.reason,
        "seconds_first": round(first, 2),
        "seconds": round(sec, 2),
    }


def with_jump(ds, jump_s: float):
    """The ranges after the campaign's middle stamped `jump_s` later (their pose offset is that much larger)."""
    t = np.asarray(ds.range_time, float)
    mid = 0.5 * (t.min() + t.max())
    return eqx.tree_at(lambda d: d.range_time, ds, np.where(t > mid, t + jump_s, t))


def summary(path: str) -> None:
    rows = [json.loads(x) for x in open(path) if x.startswith("{")]
    keys = sorted({(r["drift"], r["stated"], r["jump"]) for r in rows if "seed" in r})
    for k in keys:
        sel = [r for r in rows if "seed" in r and (r["drift"], r["stated"], r["jump"]) == k]
        fin = [r for r in sel if r["offset_s"] == r["offset_s"]]
        z = np.array([abs(r["offset_s"] - r["truth_s"]) / r["sd_s"] for r in fin])
        rounds = [r["rounds"] for r in sel if r["rounds"] is not None]
        ps = np.array([r["stretch_p"] for r in sel if r["stretch_p"] is not None])
        zm, zw = (np.median(z), z.max()) if z.size else (float("nan"), float("nan"))
        print(
            f"drift {k[0]} stated {k[1]} jump {k[2]}: {len(sel)} campaigns, NaN {len(sel) - len(fin)}, "
            f"|z| median {zm:.2f} worst {zw:.2f}, "
            f"rounds median {np.median(rounds) if rounds else float('nan'):.0f} max {max(rounds) if rounds else 0}, "
            f"min p {ps.min() if ps.size else float('nan'):.2g}, "
            f"err median {np.median([abs(r['offset_s'] - r['truth_s']) for r in fin]) if fin else float('nan'):.4f} s"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="")
    ap.add_argument("--scenario", default="small")
    ap.add_argument("--drift", type=float, nargs="*", default=[0.0])
    ap.add_argument("--stated-drift", action="store_true")
    ap.add_argument("--jump", type=float, nargs="*", default=[0.0])
    ap.add_argument("--real", action="store_true")
    ap.add_argument("--only", nargs="*", help="real recordings by label (default all)")
    ap.add_argument("--starts", type=float, nargs="*", default=[0.0])
    ap.add_argument("--options", nargs="*", default=[], help="KEY=VALUE options of offset.estimate")
    ap.add_argument("--summary")
    a = ap.parse_args()
    if a.summary:
        summary(a.summary)
        return
    options = {}
    for kv in a.options:
        k, v = kv.split("=")
        options[k] = {"true": True, "false": False}.get(v.lower(), v if not v[-1].isdigit() else float(v))
    go = in_float64(run)
    if a.real:
        from uncertainty_trajectory import real_datasets

        for label, load in real_datasets():
            if a.only and label not in a.only:
                continue
            ds = load()
            for s in a.starts:
                (out,) = go(ds, s, 0.0, options, True)
                print(json.dumps({"recording": label, "start_s": s, "options": a.options, **out}), flush=True)
    if a.seeds:
        from jaxcal.sim.trajectory import simulate

        for drift in a.drift:
            for jump in a.jump:
                for seed in parse_seeds(a.seeds):
                    truth = float(np.random.default_rng(1000 + seed).uniform(-0.3, 0.3))
                    ds = with_jump(simulate(a.scenario, seed=seed, drift=drift, time_offset_s=truth), jump)
                    outs = go(ds, 0.0, drift if a.stated_drift else 0.0, options, False, True)
                    for stated, out in zip(
                        [False, True][-len(outs) :] if a.stated_drift else [False], outs, strict=True
                    ):
                        row = {"seed": seed, "drift": drift, "stated": stated, "jump": jump, "truth_s": truth}
                        print(json.dumps({**row, "options": a.options, **out}), flush=True)


if __name__ == "__main__":
    main()
