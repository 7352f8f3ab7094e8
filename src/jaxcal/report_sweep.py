"""Parameter sweeps in reports: the sigma_r x tau surfaces of a `jaxcal sweep` file (`sweep_surfaces`)
and their report section (figure and table per surface)."""

from __future__ import annotations

import html
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxcal.errors import JaxcalError
from jaxcal.report_page import Page, fmt, table

__all__ = ["SWEEP_METRICS", "sweep_section", "sweep_surfaces"]

# metrics of a `jaxcal sweep` file drawn as surfaces (lower is better) and their labels
SWEEP_METRICS = {
    "rmse_m": "RMSE [m]",
    "final_rmse_m": "final RMSE [m]",
    "nlpl": "NLPL [nats per range]",
}


def _axis(runs: Mapping[str, np.ndarray], name: str, fixed: Mapping[str, float], n: int) -> np.ndarray:
    if f"param_{name}" in runs:
        return np.asarray(runs[f"param_{name}"], dtype=np.float64)
    if name not in fixed:
        raise JaxcalError(f"sweep: {name} is neither swept nor given as a fixed value")
    return np.full(n, float(fixed[name]))


def sweep_surfaces(
    runs: Mapping[str, np.ndarray],
    metrics: Mapping[str, np.ndarray],
    done: np.ndarray,
    *,
    metric: str = "rmse_m",
    others: str = "best",
    fixed: Mapping[str, float] | None = None,
    method: str = "",
) -> list[dict[str, Any]]:
    """Surfaces over sigma_r x tau of the runs of a parameter sweep (the layout of `jaxcal sweep`).

    One surface per (scenario, config), in the order they first appear. A cell is the mean of the
    metric over the seeds of that scenario (runs not done are left out, runs done with a NaN metric,
    i.e. no node localised, count as failed and are left out of the mean; a cell without a finite
    run is NaN). Other swept parameters (sigma_v, r_est, ...): `others="best"` takes per cell the
    combination with the lowest seed mean (its values are returned in `best_others`),
    `others="facet"` gives one surface per combination.

    Args:
        runs: `scenario`, `config` (R,) str, `seed` (R,) int, `param_<name>` (R,) swept values.
        metrics: name -> (R,) metric of every run. done: (R,) bool.
        metric: the metric to draw, one of `SWEEP_METRICS`. others: "best" or "facet".
        fixed: values of sigma_r [m] / tau used when one of them is not swept.
        method: filter name for the titles ("pgp", "parametric").

    Returns:
        Dicts for `write_report(sweeps=...)`: `sigma_r` (S,) [m], `tau` (T,), `rmse` (S, T) the
        metric (whatever `metric` is), `metric`, `label`, `title`, `n_runs`, `n_done`, `n_failed`
        (S, T) counts, `seeds`, `facet` {name: value}, `best_others` {name: (S, T) values}.
    """
    if metric not in SWEEP_METRICS:
        raise JaxcalError(f"sweep metric: one of {', '.join(SWEEP_METRICS)}; got {metric!r}")
    if others not in ("best", "facet"):
        raise JaxcalError(f"sweep others: best or facet; got {others!r}")
    if metric not in metrics:
        raise JaxcalError(f"sweep: no metric {metric!r} (has {', '.join(sorted(metrics))})")
    done = np.asarray(done, dtype=bool)
    n = done.size
    swept = [k[len("param_") :] for k in runs if k.startswith("param_")]
    if "sigma_r" not in swept and "tau" not in swept:
        raise JaxcalError(
            f"sweep: neither sigma_r nor tau is swept (swept: {', '.join(swept) or 'nothing'}); "
            "no sigma_r x tau surface to draw"
        )
    fixed = dict(fixed or {})
    sig, tau = _axis(runs, "sigma_r", fixed, n), _axis(runs, "tau", fixed, n)
    rest = [name for name in swept if name not in ("sigma_r", "tau")]
    combo = np.column_stack([np.asarray(runs[f"param_{k}"], np.float64) for k in rest] or [np.zeros(n)])
    _, combo_id = np.unique(combo, axis=0, return_inverse=True)
    combo_id = combo_id.reshape(-1)
    value = np.where(done, np.asarray(metrics[metric], dtype=np.float64), np.nan)
    scen = np.asarray(runs["scenario"]).astype(str)
    conf = np.asarray(runs.get("config", np.full(n, ""))).astype(str)
    seed = np.asarray(runs.get("seed", np.zeros(n, np.int64)))
    out = []
    for sc, cf in dict.fromkeys(zip(scen, conf, strict=True)):
        in_group = (scen == sc) & (conf == cf)
        facets = sorted(set(combo_id[in_group])) if others == "facet" and rest else [None]
        for fc in facets:
            sel = in_group if fc is None else in_group & (combo_id == fc)
            s_vals, t_vals = np.unique(sig[sel]), np.unique(tau[sel])
            c_vals = np.unique(combo_id[sel])
            si = np.searchsorted(s_vals, sig)
            ti = np.searchsorted(t_vals, tau)
            ci = np.searchsorted(c_vals, combo_id)
            shape = (s_vals.size, t_vals.size, c_vals.size)
            total, cnt, fin = np.zeros(shape), np.zeros(shape, np.int64), np.zeros(shape, np.int64)
            n_runs = np.zeros(shape[:2], np.int64)
            for r in np.flatnonzero(sel):
                idx = (si[r], ti[r], ci[r])
                n_runs[idx[:2]] += 1
                if done[r]:
                    cnt[idx] += 1
                    if np.isfinite(value[r]):
                        fin[idx] += 1
                        total[idx] += value[r]
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(fin > 0, total / np.maximum(fin, 1), np.nan)
            pick = np.argmin(np.where(np.isfinite(mean), mean, np.inf), axis=2)  # best other combo
            surf = np.take_along_axis(mean, pick[..., None], axis=2)[..., 0]
            first_of = {c: np.flatnonzero(combo_id == c)[0] for c in c_vals}
            best_others = {}
            if rest and fc is None:
                for k, name in enumerate(rest):
                    vals = np.array([combo[first_of[c], k] for c in c_vals])
                    best_others[name] = np.where(np.isfinite(surf), vals[pick], np.nan)
            facet = {} if fc is None else {name: float(combo[first_of[fc], k]) for k, name in enumerate(rest)}
            seeds = sorted({int(x) for x in seed[sel]})
            where = sc + (f"/{cf}" if cf else "")
            extra = ", ".join(f"{k} {v:g}" for k, v in facet.items())
            title = f"{method + ': ' if method else ''}{where}" + (f" ({extra})" if extra else "")
            if len(seeds) > 1:
                title += f", mean of {len(seeds)} seeds"
            out.append(
                {
                    "sigma_r": s_vals,
                    "tau": t_vals,
                    "rmse": surf,
                    "metric": metric,
                    "label": SWEEP_METRICS[metric],
                    "title": title,
                    "scenario": sc,
                    "config": cf,
                    "seeds": seeds,
                    "facet": facet,
                    "n_runs": n_runs,
                    "n_done": cnt.sum(axis=2),
                    "n_failed": (cnt - fin).sum(axis=2),
                    "best_others": best_others,
                }
            )
    return out


def _sweep_cell(sw: Mapping[str, Any], r: np.ndarray, others: dict, a: int, b: int) -> str:
    """Table text of cell (a, b): value, the best other parameters, runs not done or failed."""
    txt = fmt(r[a, b], 3)
    if others:
        txt += " (" + ", ".join(f"{k} {v[a, b]:g}" for k, v in others.items()) + ")"
    if "n_done" in sw and "n_runs" in sw and sw["n_done"][a][b] < sw["n_runs"][a][b]:
        txt += f" [{sw['n_done'][a][b]}/{sw['n_runs'][a][b]} done]"
    if "n_failed" in sw and sw["n_failed"][a][b]:
        txt += f" [{sw['n_failed'][a][b]} failed]"
    return txt


def sweep_section(page: Page, sweeps: Sequence[Mapping[str, Any]], numbers: dict) -> None:
    from jaxcal import plot

    page.h2("Parameter sweeps: sigma_r × tau")
    numbers["sweeps"] = []
    for i, sw in enumerate(sweeps):
        r = np.asarray(sw["rmse"], dtype=np.float64)
        s = np.asarray(sw["sigma_r"], dtype=np.float64)
        t = np.asarray(sw["tau"], dtype=np.float64)
        if r.shape != (s.size, t.size):
            raise JaxcalError(f"sweep {i}: rmse shape {r.shape} is not (sigma_r, tau) = ({s.size}, {t.size})")
        metric = sw.get("metric", "rmse_m")
        label = sw.get("label", SWEEP_METRICS.get(metric, metric))
        name = sw.get("title", "")
        best = np.unravel_index(np.nanargmin(r), r.shape) if np.isfinite(r).any() else None
        others = {k: np.asarray(v, np.float64) for k, v in (sw.get("best_others") or {}).items()}
        entry: dict[str, Any] = {
            "title": name,
            "metric": metric,
            "sigma_r_m": s,
            "tau": t,
            "values": r,
            "best": None
            if best is None
            else {
                "sigma_r_m": float(s[best[0]]),
                "tau": float(t[best[1]]),
                metric: float(r[best]),
                **{k: float(v[best]) for k, v in others.items()},
            },
        }
        for key in ("scenario", "config", "seeds", "facet", "n_runs", "n_done", "n_failed"):
            if key in sw:
                entry[key] = sw[key]
        if others:
            entry["best_others"] = others
        numbers["sweeps"].append(entry)
        page.raw(f"<h3>{html.escape(name or f'sweep {i}')}</h3>")
        page.figure(
            plot.sweep_surface(s, t, r, name, label=label),
            f"sweep_{i}",
            f"{label} over sigma_r × tau{': ' + name if name else ''} (star: lowest).",
        )

        rows = [[f"{s[a]:g}"] + [_sweep_cell(sw, r, others, a, b) for b in range(t.size)] for a in range(s.size)]
        page.raw(table(["sigma_r [m] ↓ tau →"] + [f"{v:g}" for v in t], rows, "num"))
        notes = []
        if best is not None:
            notes.append(f"lowest {label}: {r[best]:.3f} at sigma_r {s[best[0]]:g} m, tau {t[best[1]]:g}")
        if "seeds" in sw and len(sw["seeds"]) > 1:
            notes.append(f"cells are the mean over seeds {', '.join(map(str, sw['seeds']))}")
        if others:
            notes.append(
                f"other swept parameters ({', '.join(others)}): per cell the value with the lowest mean, in brackets"
            )
        if "n_failed" in sw and np.sum(sw["n_failed"]):
            notes.append("failed runs (no node localised) are left out of the means")
        if notes:
            page.p("; ".join(notes) + ".")
