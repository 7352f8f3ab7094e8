"""`jaxcal info FILE [--json] [--quiet]`: a readable summary of any file jaxcal writes (contract files,
sweep stores, record journals, tune parameter files)."""

from __future__ import annotations


def add_arguments(p) -> None:
    from jaxcal.commands._common import add_output_flags

    p.add_argument("file", help="a file written by jaxcal (contract HDF5, sweep store, journal, params JSON)")
    add_output_flags(p)


def time_is_index(t) -> bool:
    """Whether epoch times are whole numbers stepping by whole numbers: round indices, not seconds."""
    import numpy as np

    t = np.asarray(t, float)
    return t.size > 1 and bool(np.all(t == np.round(t))) and bool(np.all(np.diff(t) >= 1))


def summarise(obj) -> dict:
    """Summary of a dataset or result as a plain dict."""
    import numpy as np

    from jaxcal.commands._common import kind_of

    kind = kind_of(obj)
    out: dict = {"format": kind}
    if kind == "mesh":
        rng = obj.range
        measured = np.isfinite(rng)
        k, n = obj.n_epochs, obj.n_nodes
        pairs = max(n * (n - 1), 1)
        from jaxcal.mesh.identify import identify_ranges, measured_pairs

        pair_seen = measured_pairs(rng)
        never = [[obj.node_ids[i], obj.node_ids[j]] for i in range(n) for j in range(i + 1, n) if not pair_seen[i, j]]
        named = (dict(obj.configs) or {"default": (0, 1, 2)}) if n >= 3 else {}
        # what each frame configuration lets a method place (`jaxcal.mesh.identify`)
        frames = {c: identify_ranges(rng, v, ids=obj.node_ids) for c, v in named.items()}
        out.update(
            name=obj.name,
            nodes=list(obj.node_ids),
            epochs=k,
            time_span_s=[float(obj.time[0]), float(obj.time[-1])] if k else None,
            time_is_index=time_is_index(obj.time),
            ranges=int(measured.sum()),
            truth=obj.truth is not None and bool(np.isfinite(obj.truth).all(axis=1).any()),
            los_known=obj.los is not None,
            configs={c: list(v) for c, v in obj.configs},
            # availability: fraction of (epoch, other node) slots with a range from or to this node
            availability={
                nid: float((measured[:, i, :] | measured[:, :, i]).sum() / max(k * (n - 1), 1))
                for i, nid in enumerate(obj.node_ids)
            },
            pair_coverage=float((measured.any(axis=0).sum()) / pairs),
            never_ranged=never,
            frames={c: {"fixed": int(f.n_fixed), "not_fixed": [r for r in f.reason if r]} for c, f in frames.items()},
        )
    elif kind == "trajectory":
        r = obj.n_ranges
        out.update(
            name=obj.name,
            anchors=list(obj.anchor_ids),
            tags=list(obj.tag_ids),
            poses=int(obj.pose_time.shape[0]),
            pose_span_s=[float(obj.pose_time[0]), float(obj.pose_time[-1])],
            ranges=r,
            range_span_s=[float(obj.range_time[0]), float(obj.range_time[-1])] if r else None,
            truth=obj.anchor_truth is not None and bool(np.isfinite(obj.anchor_truth).all(axis=1).any()),
            ranges_per_anchor={a: int((obj.range_anchor == i).sum()) for i, a in enumerate(obj.anchor_ids)},
            orientation=obj.pose_orientation is not None,
        )
    else:
        finite = np.isfinite(obj.position)
        est = finite.all(axis=1)
        out.update(
            name=obj.name,
            method=obj.method,
            dataset=obj.dataset,
            frame=obj.frame,
            software=obj.software,
            ids=list(obj.ids),
            dims=int(obj.position.shape[1]),
            estimated=int(est.sum()),
            partial=int((finite.any(axis=1) & ~est).sum()),  # a coordinate the data cannot fix left NaN
            covariance=obj.covariance is not None,
            track_epochs=None if obj.track_time is None else int(obj.track_time.shape[0]),
            params=dict(obj.params),
        )
    return out


def run(args) -> int:
    from jaxcal.commands._common import load, print_json
    from jaxcal.commands._files import identify, journal_summary, params_summary, sweep_summary

    kind = identify(args.file)
    if kind in ("mesh", "trajectory", "result"):
        s = summarise(load(args.file))
    elif kind == "sweep":
        s = sweep_summary(args.file)
    elif kind == "journal":
        s = journal_summary(args.file)
    elif kind == "params":
        s = params_summary(args.file)
    else:
        import json
        from pathlib import Path

        s = {"format": "summary", "keys": sorted(json.loads(Path(args.file).read_text(encoding="utf-8")))}
    if args.json:
        print_json(s)
        return 0
    if args.quiet:
        return 0
    if kind not in ("mesh", "trajectory", "result"):
        _print_other(args.file, s)
        return 0
    kind = s["format"]
    print(f"{args.file}: jaxcal {kind} file '{s['name']}'")
    if kind == "mesh":
        t = s["time_span_s"]
        if t and s["time_is_index"]:  # e.g. dwm1001-autocal: the rows of the files, not a clock
            span = f"epoch index {t[0]:.0f}..{t[1]:.0f} (whole numbers: round indices, not seconds)"
        else:
            span = f"{t[0]:.3f} .. {t[1]:.3f} s ({t[1] - t[0]:.1f} s)" if t else "empty"
        print(f"  nodes: {len(s['nodes'])}   epochs: {s['epochs']}   ranges: {s['ranges']}   time: {span}")
        print(
            f"  truth: {'yes' if s['truth'] else 'no'}   LOS matrix: {'yes' if s['los_known'] else 'no'}"
            f"   pairs ever measured: {100 * s['pair_coverage']:.1f} %"
        )
        if s["configs"]:
            print("  configurations: " + ", ".join(f"{c}={tuple(v)}" for c, v in s["configs"].items()))
        nr = s["never_ranged"]
        print(f"  pairs never ranged: {len(nr)}" + (": " + ", ".join(f"{a}-{b}" for a, b in nr) if nr else ""))
        for c, f in s["frames"].items():
            why = "; ".join(f["not_fixed"])
            print(f"  frame {c}: the ranges fix {f['fixed']}/{len(s['nodes'])} nodes" + (f" ({why})" if why else ""))
        print("  availability per node (share of epoch x peer slots with a range):")
        for nid, a in s["availability"].items():
            print(f"    {nid:>12s}  {100 * a:6.1f} %")
    elif kind == "trajectory":
        t = s["pose_span_s"]
        print(f"  anchors: {len(s['anchors'])}   tags: {len(s['tags'])}   poses: {s['poses']}   ranges: {s['ranges']}")
        print(
            f"  poses: {t[0]:.3f} .. {t[1]:.3f} s   orientation: {'yes' if s['orientation'] else 'no'}"
            f"   anchor truth: {'yes' if s['truth'] else 'no'}"
        )
        print("  ranges per anchor: " + ", ".join(f"{a}={c}" for a, c in s["ranges_per_anchor"].items()))
    else:
        print(f"  method: {s['method']}   dataset: {s['dataset']}   frame: {s['frame']}   software: {s['software']}")
        print(
            f"  estimates: {s['estimated']}/{len(s['ids'])} ({s['dims']}-D)"
            + (f", {s['partial']} more with a coordinate not fixed" if s["partial"] else "")
            + "   covariance: "
            f"{'yes' if s['covariance'] else 'no'}   track epochs: {s['track_epochs'] or 'none'}"
        )
        if s["params"]:
            print("  params: " + ", ".join(f"{k}={v}" for k, v in s["params"].items()))
    return 0


def _print_other(path: str, s: dict) -> None:
    kind = s["format"]
    if kind == "sweep":
        print(f"{path}: jaxcal sweep store, method {s['method']}: {s['done']}/{s['runs']} runs done")
        print(f"  scenarios: {', '.join(s['scenarios'])}   seeds: {len(s['seeds'])}")
        for k, v in s["swept"].items():
            print(f"  swept {k}: {', '.join(f'{x:g}' for x in v)}")
        if s["fixed_params"]:
            print(f"  fixed: {s['fixed_params']}")
        for k, v in s["metrics"].items():
            print(f"  {k}: " + ("no run done" if v is None else f"{v[0]:.3f} .. {v[1]:.3f}"))
    elif kind == "journal":
        h = s["header"]
        print(
            f"{path}: jaxcal record journal ({h.get('protocol', '?')}), {s['frames']} frames"
            + (f", torn tail of {s['torn_bytes']} bytes" if s["torn_bytes"] else "")
        )
        print(f"  rebuild it with: jaxcal record --replay {path} -o OUT.h5")
    elif kind == "params":
        print(f"{path}: jaxcal parameters for --method {s['method']} (from jaxcal tune)")
        print("  params: " + ", ".join(f"{k}={v}" for k, v in s["params"].items()))
        t = s["tuning"]
        if t:
            print(
                f"  tuned on {t.get('dataset', '?')} with objective {t.get('objective', t.get('objective_name', '?'))}"
            )
    else:
        print(f"{path}: JSON summary written by jaxcal, keys: {', '.join(s['keys'])}")
