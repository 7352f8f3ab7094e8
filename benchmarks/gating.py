"""Benchmark: UWB range-zone gating for one-shot place recognition (second paper, Table II).

A simulated repetitive container yard (`jaxcal.sim.places`: 600 x 450 m, ~13,600 keyframes with
256-D descriptors whose scenery repeats every container and every aisle) and a query run along the
same aisles with a lateral offset. For each configuration (anchors' calibration error x number of
anchors heard) it reports:

- success rate: the top-1 candidate lies within 8.5 m of the true query position (paper, IV-E),
  gated and ungated (full search), on the same queries; mean position error of the successes;
- time per query [ms], gated (`gating.search`: zone index, gather, match the admissible keyframes
  only) and full (`gating.search_full`: match every keyframe). `ms_gated` / `ms_full` are one-shot
  latencies as in the paper: one query per call (`gating.search_one`, whose capacity is chosen on
  the device by `lax.switch`, and `gating.search_one_full`), the whole public call timed with
  `jax.block_until_ready`, best of 20 (quick: 10) per query after a warm-up call that compiles
  (compile time reported apart), mean over 30 (quick: 15) queries spread along the run.
  `ms_gated_batch` / `ms_full_batch`: the whole batch of queries in one call, best of `--repeats`,
  divided by the number of queries (the full search is then one matrix product, which BLAS does
  very efficiently). `ms_masked_batch`: the zone mask over all keyframes, then a masked top-k
  (same descriptor work as full: gating by masking alone saves nothing).

Calibration error: anchors = truth + Gaussian error of the given RMS size, with the honest
covariance (error^2 / 3) I, so that the zones widen by k_sigma * sigma. With `--gp` (default when
the GP method is registered and importable, not with --quick) also GP-calibrated anchors
(`jaxcal calibrate --method gp`): `gp-campus` = the 10 anchors of the simulated `campus` scenario
(same 600 x 450 m area) calibrated from its drive (`--campus-drift`), placed in the yard (whose
ranges are then simulated to those anchors; `truth-campus` is the same with exact anchors), and
`gp-yard` = the yard's own anchors calibrated from the prior mapping run (the keyframe trajectory
and its ranges), as in the paper's pipeline.
Heard anchors: the n shortest measured ranges of each query (all heard ranges carry the LOS / NLOS
error mixture of `jaxcal.sim.channel`, NLOS share 0.2, including its 20-25 m outliers).

Usage: python benchmarks/gating.py [--quick] [--json] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.sim.places import PlaceConfig, perturb_anchors, simulate_places
from jaxcal.trajectory import gating

SUCCESS_M = 8.5


def best_time(fn, repeats: int) -> float:
    """Best wall time [s] of `repeats` calls of fn() (fn blocks until its result is ready)."""
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def keep_shortest(ranges: np.ndarray, n: int) -> np.ndarray:
    """Keep the n shortest finite ranges of each row (the anchors heard best), NaN elsewhere."""
    out = np.full_like(ranges, np.nan)
    order = np.argsort(np.where(np.isfinite(ranges), ranges, np.inf), axis=1)[:, :n]
    rows = np.arange(ranges.shape[0])[:, None]
    out[rows, order] = ranges[rows, order]
    return out


def score(kf_pos, idx, truth):
    """(success rate, mean error of the successes [m]) of top-1 candidates `idx` (-1 = none)."""
    ok = idx >= 0
    err = np.where(ok, np.linalg.norm(kf_pos[np.maximum(idx, 0)] - truth, axis=1), np.inf)
    hit = err < SUCCESS_M
    return float(hit.mean()), float(err[hit].mean()) if hit.any() else float("nan")


def gp_anchors(scene, seed: int):
    """Anchors calibrated by the registered GP method on the simulated prior run, or None."""
    try:
        from jaxcal.io import hdf5
        from jaxcal.io.places import write_places_files
        from jaxcal.methods import calibrate
    except Exception:  # noqa: BLE001 - the GP issue may not have landed
        return None
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        db_file, _, _ = write_places_files(d, scene, 0.0, seed)
        ds = hdf5.read(db_file)
    try:
        res = calibrate(ds, "gp")
    except Exception as e:  # noqa: BLE001
        print(f"# gp calibration unavailable: {type(e).__name__}: {e}", file=sys.stderr)
        return None
    return res.position, res.covariance


def campus_gp_anchors(seed: int, drift: float):
    """(truth, GP estimate, covariance) of the simulated `campus` anchors; None if unavailable."""
    try:
        from jaxcal.methods import calibrate
        from jaxcal.sim.trajectory import simulate
    except Exception:  # noqa: BLE001 - the campus scenario may not have landed
        return None
    try:
        ds = simulate("campus", seed, drift)
        res = calibrate(ds, "gp")
    except Exception as e:  # noqa: BLE001
        print(f"# campus gp calibration unavailable: {type(e).__name__}: {e}", file=sys.stderr)
        return None
    return ds.anchor_truth, res.position, res.covariance


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer configurations and queries (< 2 min)")
    ap.add_argument("--json", action="store_true", help="one JSON object per configuration")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument(
        "--gp",
        choices=("auto", "yes", "no"),
        default="auto",
        help="also GP-calibrated anchors (auto: if available, not with --quick: takes minutes)",
    )
    ap.add_argument("--descriptor-dim", type=int, default=256, help="F (cost per keyframe match)")
    ap.add_argument("--campus-drift", type=float, default=0.0, help="odometry drift of the campus run")
    args = ap.parse_args(argv)

    quick = args.quick
    repeats = args.repeats or (3 if quick else 5)
    n_queries = 200 if quick else 500
    errors = [0.0, 2.0, 5.0] if quick else [0.0, 1.0, 2.0, 5.0, 10.0]
    n_single = 15 if quick else 30
    lat_repeats = 10 if quick else 20  # one-shot calls are short: many repeats beat load spikes
    cfg = PlaceConfig(descriptor_dim=args.descriptor_dim)
    params = gating.GateParams()  # delta 3 m, k_sigma 2, range_rel 0.01

    t0 = time.perf_counter()
    scene = simulate_places(args.seed, cfg, n_queries=n_queries)
    sim_s = time.perf_counter() - t0
    kf_pos = scene.keyframe_position
    truth = scene.query_position
    db = gating.KeyframeDB.build(kf_pos, scene.keyframe_descriptor)
    qdesc = jnp.asarray(scene.query_descriptor)
    q = qdesc.shape[0]
    device = jax.devices()[0]
    common = {
        "device": f"{device.platform}:{device.device_kind}",
        "cpu_count": os.cpu_count(),
        "keyframes": db.n_keyframes,
        "descriptor_dim": int(qdesc.shape[1]),
        "queries": q,
        "anchors_total": int(scene.anchor_truth.shape[0]),
        "area_m": [cfg.width_m, cfg.height_m],
        "delta_m": float(params.delta_m),
        "k_sigma": float(params.k_sigma),
        "range_rel": float(params.range_rel),
        "repeats": repeats,
        "seed": args.seed,
    }

    # Ungated baseline, once.
    t0 = time.perf_counter()
    full = jax.block_until_ready(gating.search_full(db, qdesc, top_k=1))
    full_compile_s = time.perf_counter() - t0
    full_s = best_time(lambda: jax.block_until_ready(gating.search_full(db, qdesc, top_k=1)), repeats)
    succ_full, err_full = score(kf_pos, np.asarray(full.index[:, 0]), truth)
    single = np.linspace(0, q - 1, n_single).astype(int)
    one = [qdesc[i] for i in single]
    jax.block_until_ready(gating.search_one_full(db, one[0], 1))
    full_single_ms = 1e3 * float(
        np.mean(
            [best_time(lambda x=x: jax.block_until_ready(gating.search_one_full(db, x, 1)), lat_repeats) for x in one]
        )
    )

    masked_fn = jax.jit(jax.vmap(gating.rank_masked, in_axes=(None, None, 0, 0, None, None)), static_argnums=5)

    # (label, scene whose anchors and ranges are used, estimated positions, covariances)
    rng = np.random.default_rng(args.seed + 100)
    calibrations = [("controlled", scene, *perturb_anchors(rng, scene.anchor_truth, e)) for e in errors]
    if args.gp == "yes" or (args.gp == "auto" and not quick):
        found = 0
        # GP of the campus scenario (its 10 anchors, same 600 x 450 m area) placed in the yard
        campus = campus_gp_anchors(args.seed, args.campus_drift)
        if campus is not None:
            truth_c, pos_c, cov_c = campus
            scene_c = simulate_places(args.seed, cfg, n_queries=n_queries, anchors=truth_c)
            calibrations.append(("truth-campus", scene_c, truth_c, np.zeros_like(cov_c)))
            calibrations.append(("gp-campus", scene_c, pos_c, cov_c))
            found += 1
        # GP on the yard's own prior mapping run (the keyframe trajectory and its ranges)
        gp = gp_anchors(scene, args.seed)
        if gp is not None:
            calibrations.append(("gp-yard", scene, *gp))
            found += 1
        if not found and args.gp == "yes":
            print("gp anchors requested but unavailable", file=sys.stderr)
            return 1

    rows = []
    for kind, scn, a_pos, a_cov in calibrations:
        a_err = np.linalg.norm(a_pos - scn.anchor_truth, axis=1)
        anchors = gating.Anchors.from_estimate(a_pos, a_cov)
        t0 = time.perf_counter()
        index = jax.block_until_ready(gating.ZoneIndex.build(db, anchors))
        index_ms = 1e3 * (time.perf_counter() - t0)
        for n_heard in (1, 2, 3):
            ranges = keep_shortest(scn.query_range.astype(np.float64), n_heard)
            r_j = jnp.asarray(ranges)

            def gated(r=ranges, an=anchors, ix=index):
                return jax.block_until_ready(gating.search(db, ix, an, qdesc, r, params, top_k=1))

            t0 = time.perf_counter()
            res = gated()
            compile_s = time.perf_counter() - t0
            gated_s = best_time(gated, repeats)
            jax.block_until_ready(masked_fn(db, anchors, r_j, qdesc, params, 1))
            masked_s = best_time(
                lambda an=anchors, r=r_j: jax.block_until_ready(masked_fn(db, an, r, qdesc, params, 1)),
                repeats,
            )
            succ, err = score(kf_pos, np.asarray(res.index[:, 0]), truth)
            times = []
            for i in single:
                r_i = r_j[i]

                def one_query(r_i=r_i, q_i=qdesc[i], an=anchors, ix=index):
                    return jax.block_until_ready(gating.search_one(db, ix, an, r_i, q_i, params, 1))

                one_query()  # compiles once (all capacity branches), then cached
                times.append(best_time(one_query, lat_repeats))
            single_ms = 1e3 * float(np.mean(times))
            heard = np.isfinite(ranges).sum(1)
            los_only = np.all(scn.query_los | ~np.isfinite(ranges), axis=1)
            row = {
                "calibration": kind,
                "anchor_error_rms_m": float(np.sqrt(np.mean(a_err**2))),
                "anchor_error_mean_m": float(a_err.mean()),
                "anchor_error_horizontal_mean_m": float(
                    np.linalg.norm((a_pos - scn.anchor_truth)[:, :2], axis=1).mean()
                ),
                "anchor_sigma_mean_m": float(np.asarray(anchors.sigma).mean()),
                "anchors_in_scene": int(scn.anchor_truth.shape[0]),
                "anchors_heard": n_heard,
                "mean_anchors_heard": float(heard.mean()),
                "success_gated": succ,
                "success_full": succ_full,
                "error_gated_m": err,
                "error_full_m": err_full,
                "ms_gated": single_ms,
                "ms_full": full_single_ms,
                "speedup": full_single_ms / single_ms,
                "ms_gated_batch": 1e3 * gated_s / q,
                "ms_full_batch": 1e3 * full_s / q,
                "ms_masked_batch": 1e3 * masked_s / q,
                "speedup_batch": full_s / gated_s,
                "latency_queries": int(n_single),
                "latency_repeats": lat_repeats,
                "mean_admissible": float(np.asarray(res.n_admissible).mean()),
                "admissible_share": float(np.asarray(res.n_admissible).mean() / db.n_keyframes),
                "success_gated_los_queries": float(
                    np.mean(
                        (
                            np.linalg.norm(kf_pos[np.maximum(np.asarray(res.index[:, 0]), 0)] - truth, axis=1)
                            < SUCCESS_M
                        )[los_only]
                    )
                )
                if los_only.any()
                else float("nan"),
                "compile_s": compile_s,
                "full_compile_s": full_compile_s,
                "index_build_ms": index_ms,
                "sim_s": sim_s,
                **common,
            }
            rows.append(row)
            if args.json:
                print(
                    json.dumps(
                        {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
                    ),
                    flush=True,
                )
    if not args.json:
        print(
            f"# {common['device']}, {db.n_keyframes} keyframes x {common['descriptor_dim']}-D, "
            f"{q} queries, "
            f"best of {repeats}; full search: success {succ_full:.1%}, "
            f"{full_single_ms:.3f} ms/query "
            f"one-shot, {1e3 * full_s / q:.3f} ms/query batched"
        )
        print(
            f"{'calib':>10} {'err_m':>6} {'heard':>5} {'succ_g':>7} {'succ_f':>7} "
            f"{'err_g':>6} {'err_f':>6} "
            f"{'ms_g':>7} {'ms_f':>7} {'x':>5} {'msb_g':>7} {'msb_f':>7} {'msb_msk':>7} {'adm%':>6}"
        )
        for r in rows:
            print(
                f"{r['calibration']:>10} {r['anchor_error_rms_m']:6.2f} {r['anchors_heard']:5d} "
                f"{r['success_gated']:7.1%} {r['success_full']:7.1%} {r['error_gated_m']:6.2f} "
                f"{r['error_full_m']:6.2f} {r['ms_gated']:7.3f} {r['ms_full']:7.3f} "
                f"{r['speedup']:5.1f} "
                f"{r['ms_gated_batch']:7.3f} {r['ms_full_batch']:7.3f} {r['ms_masked_batch']:7.3f} "
                f"{100 * r['admissible_share']:6.2f}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
