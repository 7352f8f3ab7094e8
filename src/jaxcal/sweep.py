"""Parameter sweeps of the grid filter: parameters x scenarios x seeds as vmapped, sharded batches.

A sweep is a list of runs (`plan`): every scenario (a simulated scenario with its seeds, or a
dataset) crossed with the product of the swept parameter values. Swept parameters are the numeric
fields of `pgp.FilterParams` (sigma_r, sigma_v, tau, r_est, v, alpha, p_out, nlos_weight,
nlos_mean_m): they are arrays, so a whole batch of values is one `jax.vmap` of the jitted
filter, and new values never recompile. Fixed parameters (`cell_m`, `top_k`, `max_hyp`, ...)
are static: one compilation per group.

Runs whose datasets have the same number of nodes and epochs form a group and run on one common
grid: the largest of their `prepare` grids (a dataset whose own grid is smaller gets a few more
cells of uniform prior at the border; with a single dataset the grid is exactly `run_pgp`'s).

Batches hold `batch_size` runs per device and are laid out along a 1-D mesh of `jax.devices()`
(`NamedSharding`, run i of a batch on device i // batch_size); under `jax.distributed` the mesh
spans the devices of all processes, every process builds the same batches and computes the runs
of its own devices, and the metrics are gathered to every process (`process_allgather`), so that
process 0 can write them.

Execution (`SweepSpec.execution`, `jaxcal sweep --execution`), chosen per backend by "auto":

- "sequential" (auto on CPU): every device runs its runs one after the other, each exactly as a
  single `run_pgp` (`pgp.run_chunked`: the windowed fast path, whose `lax.cond`s stay branches),
  then `reduce_metrics`. A sweep then costs what its runs cost one by one, and its numbers are
  bit-for-bit those of `run_pgp` with `mirror="off"`: a sweep measures the filter, whose final
  layout is what `tune` differentiates; pgp's mirror check (a host-side search after the filter,
  `pgp.mirror`, on by default in `calibrate`) is not applied, and the sweep says so in one
  line. Several local devices run their runs in one thread each.
  Under `vmap` a `cond` whose predicate differs between runs evaluates both branches, i.e. every
  epoch of every run would also pay the full-grid epoch: 10-30x a single run on CPU.
- "vmap" (auto on GPU/TPU): vmapped batches (the last one padded with copies of a run) sharded
  over the devices: wide batches keep an accelerator busy. On the windowed fast path the batch
  runs in lockstep chunks (`mesh.lockstep`): the host decides each step's branch for the whole
  batch (a window-only chunk for the runs whose windows hold, a full-grid epoch only for the runs
  that need one), so runs do not pay the full grid at every epoch. The one-scan likelihoods
  ("direct", "dense") and multi-process sweeps run one vmapped `pgp.run_filter` per batch (both
  branches of every cond). Same metrics as "sequential" up to rounding;
  `benchmarks/sweep_batching.py` measures runs/s against batch size.

Large sites (issue #26): a dataset that `calibrate --method pgp` runs on node-local grids
(`pgp.uses_local`: the site wider than one node-local grid, `grid_mode="auto"`) is not put on a common
grid: each of its runs is one `pgp.run_pgp`, exactly as `calibrate` runs it (node-local grids, the
fitted range offset of `bias`), one after the other whatever the execution (every process of a
multi-process sweep computes them all). Their `nlpl` is NaN (the node-local grids normalise each
node's evidence over its own wide grid only, so it is not the global grid's figure); one warning line
says so.

Metrics per run (`METRICS`, all in the configuration frame, a0 excluded): `rmse_m` (every localised
epoch estimate, as `jaxcal evaluate`), `final_rmse_m` (the final positions), `availability` (share
of (epoch, node) estimates that exist), `localised` (nodes with a final estimate, of N - 1) and
`nlpl` (negative log predictive likelihood of the ranges, nats per range factor,
`tune.neg_log_predictive`).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxcal.data import MeshDataset
from jaxcal.errors import JaxcalError
from jaxcal.executables import release_if_crowded
from jaxcal.mesh import grid as G
from jaxcal.mesh import pgp
from jaxcal.params import with_overrides
from jaxcal.tune import (
    final_rmse,
    grid_span_m,
    neg_log_predictive,
    track_rmse,
    truth_in_filter_order,
    window,
)

__all__ = [
    "SWEEPABLE",
    "METRICS",
    "EXECUTIONS",
    "resolve_execution",
    "Scenario",
    "SweepSpec",
    "parse_spec",
    "Plan",
    "plan",
    "Group",
    "LocalGroup",
    "build_groups",
    "local_metrics",
    "run_metrics",
    "reduce_metrics",
    "run_single",
    "run_batch",
    "execute",
]

SWEEPABLE = ("tau", "r_est", "sigma_r", "v", "sigma_v", "alpha", "p_out", "nlos_weight", "nlos_mean_m")
METRICS = ("rmse_m", "final_rmse_m", "availability", "localised", "nlpl")
EXECUTIONS = ("auto", "sequential", "vmap")


def resolve_execution(execution: str = "auto", backend: str | None = None) -> str:
    """ "sequential" or "vmap": `execution` itself, or for "auto" the choice for `backend`
    (default `jax.default_backend()`): "sequential" on CPU, "vmap" on accelerators."""
    if execution not in EXECUTIONS:
        raise JaxcalError(f"execution: one of {', '.join(EXECUTIONS)}; got {execution!r}")
    if execution != "auto":
        return execution
    return "sequential" if (backend or jax.default_backend()) == "cpu" else "vmap"


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A source of datasets: `simulate` (scenario name, one dataset per seed) or `file` (a path)."""

    label: str
    simulate: str | None
    file: str | None
    config: str | None
    seeds: tuple[int, ...]
    overrides: tuple[tuple[str, object], ...] = ()


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep specification (see docs/cluster.md for the TOML form).

    Attributes:
        method: "pgp" or "parametric". epochs: window (first K epochs) or None for all.
        params: fixed parameter overrides of `PGPParams`. grid: swept name -> values.
        scenarios: the dataset sources. batch_size: runs per device in one batch (a batch holds
            batch_size x device count runs; the last one of a group is padded with copies).
        execution: "auto", "sequential" or "vmap" (module docstring); results do not depend on
            it beyond rounding, so like batch_size it is not part of a sweep's identity.
    """

    method: str
    epochs: int | None
    params: tuple[tuple[str, object], ...]
    grid: tuple[tuple[str, tuple[float, ...]], ...]
    scenarios: tuple[Scenario, ...]
    batch_size: int = 16
    execution: str = "auto"


def _need(ok: bool, msg: str) -> None:
    if not ok:
        raise JaxcalError(f"sweep spec: {msg}")


def parse_spec(doc: Mapping) -> SweepSpec:
    """Validate a sweep specification (the dict of a TOML file) and return a `SweepSpec`."""
    known = {"method", "epochs", "batch_size", "execution", "params", "grid", "scenarios"}
    extra = set(doc) - known
    _need(not extra, f"unknown keys {sorted(extra)} (known: {sorted(known)})")
    method = doc.get("method", "pgp")
    _need(method in ("pgp", "parametric"), f"method: pgp or parametric, got {method!r}")
    epochs = doc.get("epochs")
    _need(
        epochs is None or (isinstance(epochs, int) and epochs >= 1),
        f"epochs: an integer >= 1, got {epochs!r}",
    )
    bs = doc.get("batch_size", 16)
    _need(isinstance(bs, int) and bs >= 1, f"batch_size: an integer >= 1, got {bs!r}")
    execution = doc.get("execution", "auto")
    _need(
        execution in EXECUTIONS,
        f"execution: one of {', '.join(EXECUTIONS)}, got {execution!r}",
    )
    params = dict(doc.get("params", {}))
    swept = set(doc.get("grid", {}))
    _need(not (swept & set(params)), f"parameters both fixed and swept: {sorted(swept & set(params))}")
    with_overrides(pgp.PGPParams(), params)  # unknown names and bad types fail here
    grid = []
    for name, vals in dict(doc.get("grid", {})).items():
        _need(
            name in SWEEPABLE,
            f"grid.{name}: only {', '.join(SWEEPABLE)} can be swept (others recompile)",
        )
        vals = vals if isinstance(vals, list) else [vals]
        _need(
            len(vals) >= 1 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals),
            f"grid.{name}: a list of numbers",
        )
        for v in vals:  # the same range checks as a single run
            pgp.validate_params(with_overrides(pgp.PGPParams(), {**params, name: float(v)}))
        grid.append((name, tuple(float(v) for v in vals)))
    scen = doc.get("scenarios", [])
    _need(isinstance(scen, list) and len(scen) >= 1, "at least one [[scenarios]] table")
    out = []
    for k, s in enumerate(scen):
        _need(isinstance(s, dict), f"scenarios[{k}]: a table")
        extra = set(s) - {"simulate", "file", "config", "seeds", "label", "overrides"}
        _need(not extra, f"scenarios[{k}]: unknown keys {sorted(extra)}")
        _need(("simulate" in s) != ("file" in s), f"scenarios[{k}]: exactly one of simulate, file")
        seeds = s.get("seeds", [0] if "simulate" in s else [-1])
        seeds = seeds if isinstance(seeds, list) else [seeds]
        _need(
            bool(seeds) and all(isinstance(x, int) for x in seeds),
            f"scenarios[{k}].seeds: a list of integers",
        )
        _need("file" not in s or "seeds" not in s, f"scenarios[{k}]: seeds only apply to simulate")
        label = str(s.get("label", s.get("simulate") or s.get("file")))
        out.append(
            Scenario(
                label,
                s.get("simulate"),
                s.get("file"),
                s.get("config"),
                tuple(seeds),
                tuple(sorted(dict(s.get("overrides", {})).items())),
            )
        )
    return SweepSpec(method, epochs, tuple(sorted(params.items())), tuple(grid), tuple(out), bs, execution)


@dataclasses.dataclass(frozen=True)
class Plan:
    """The runs of a sweep in a fixed order (scenario, seed, then the parameter product).

    Attributes:
        dataset_of: (R,) index into `datasets` (pairs (scenario index, seed)).
        datasets: the distinct (scenario index, seed) pairs.
        values: swept name -> (R,) value of every run.
    """

    dataset_of: np.ndarray
    datasets: tuple[tuple[int, int], ...]
    values: dict

    @property
    def n_runs(self) -> int:
        return int(self.dataset_of.shape[0])


def plan(spec: SweepSpec) -> Plan:
    """Expand a spec into its runs."""
    names = [n for n, _ in spec.grid]
    combos = list(itertools.product(*(v for _, v in spec.grid))) or [()]
    ds: list = []
    ds_of: list[int] = []
    vals: dict[str, list] = {n: [] for n in names}
    for si, sc in enumerate(spec.scenarios):
        for seed in sc.seeds:
            ds.append((si, seed))
            for c in combos:
                ds_of.append(len(ds) - 1)
                for n, v in zip(names, c, strict=True):
                    vals[n].append(v)
    return Plan(
        np.asarray(ds_of, np.int64),
        tuple(ds),
        {n: np.asarray(v, np.float64) for n, v in vals.items()},
    )


class Group(eqx.Module):
    """Datasets sharing one compiled filter: common static config, stacked per-dataset arrays."""

    cfg: pgp.FilterConfig
    base: pgp.FilterParams
    inp: pgp.FilterInputs  # leading axis: dataset within the group
    logpost0: Float[Array, "d nodes nx ny"]
    truth: Float[Array, "d nodes 2"]
    members: tuple[int, ...] = eqx.field(static=True)  # indices into Plan.datasets
    span_m: float = eqx.field(static=True)


@dataclasses.dataclass(frozen=True)
class LocalGroup:
    """Datasets that `calibrate` runs on node-local grids (`pgp.uses_local`): each run is one
    `pgp.run_pgp` (`local_metrics`), never a common grid."""

    members: tuple[int, ...]  # indices into Plan.datasets
    datasets: tuple[tuple[MeshDataset, str | None], ...]  # (window of the dataset, config) per member
    params: pgp.PGPParams


def local_metrics(dataset: MeshDataset, config: str | None, params: pgp.PGPParams, method: str) -> dict[str, float]:
    """The sweep's metrics of one `pgp.run_pgp` as `calibrate` runs it (node-local grids); `nlpl` NaN."""
    res, _ = pgp.run_pgp(dataset, params, config, mode=method, posterior=False)
    order = pgp.node_order(dataset.n_nodes, dataset.config(config))
    est = jnp.asarray(np.asarray(res.track_position)[:, order])
    truth = jnp.asarray(truth_in_filter_order(dataset, config, order), est.dtype)
    have = np.isfinite(np.asarray(est)).all(-1)[:, 1:]
    return {
        "rmse_m": float(track_rmse(est, truth)),
        "final_rmse_m": float(final_rmse(est, truth)),
        "availability": float(have.mean()) if have.size else float("nan"),
        "localised": float(have[-1].sum()) if have.size else 0.0,
        "nlpl": float("nan"),
    }


def build_groups(
    datasets: Sequence[tuple[MeshDataset, str | None]], spec: SweepSpec
) -> tuple[list[Group | LocalGroup], np.ndarray]:
    """Prepare every dataset and group those with equal shapes on a common grid (those that
    `calibrate` runs on node-local grids: one `LocalGroup`).

    Args:
        datasets: one (dataset, config name) per `Plan.datasets` entry.
        spec: the sweep spec (fixed parameters, method, epochs).

    Returns:
        (groups, group_of): `group_of[d]` is the group of dataset d.
    """
    params = with_overrides(pgp.PGPParams(), dict(spec.params))
    prepared: list = []
    local: list[int] = []
    for d, (ds, config) in enumerate(datasets):
        if ds.n_epochs == 0:
            raise JaxcalError(f"{ds.name}: no epochs")
        w = window(ds, spec.epochs)
        if pgp.uses_local(w, params, config, spec.method):
            local.append(d)
            prepared.append((w, config))
            continue
        cfg, prm, inp, lp0, order = pgp.prepare(w, params, config, spec.method)
        prepared.append((w, config, cfg, prm, inp, order))
    keys: dict[tuple[int, int], list[int]] = {}
    for d, (w, *_rest) in enumerate(prepared):
        if d not in local:
            keys.setdefault((w.n_nodes, w.n_epochs), []).append(d)
    groups: list = []
    group_of = np.zeros(len(prepared), np.int64)
    if local:
        import logging

        group_of[local] = len(groups)
        groups.append(LocalGroup(tuple(local), tuple(prepared[d] for d in local), params))
        logging.getLogger("jaxcal").warning(
            "sweep: %d dataset(s) wider than one node-local grid run as calibrate runs them (node-local "
            "grids, one run at a time): their nlpl is NaN",
            len(local),
        )
    if keys and params.mirror != "off":
        import logging

        logging.getLogger("jaxcal").warning(
            "sweep: the metrics are the filter's; pgp's mirror check (mirror=%s in calibrate) is not applied "
            "to sweep runs (set mirror=off to silence this)",
            params.mirror,
        )
    for members in keys.values():
        grid = max((prepared[d][2].grid for d in members), key=lambda g: g.n_half)
        cfg = dataclasses.replace(prepared[members[0]][2], grid=grid)
        inps, lps, truths = [], [], []
        for d in members:
            w, config, _, prm, inp, order = prepared[d]
            mask = jnp.asarray(G.region_masks(grid, w.n_nodes))
            lp0 = jnp.where(mask, 0.0, -jnp.inf).astype(prm.sigma_r.dtype)
            lps.append(lp0 - jax.nn.logsumexp(lp0, axis=(1, 2), keepdims=True))
            inps.append(dataclasses.replace(inp, mask=mask))
            truths.append(jnp.asarray(truth_in_filter_order(w, config, order), prm.sigma_r.dtype))
            group_of[d] = len(groups)
        stack = lambda *xs: jnp.stack(xs)  # noqa: E731
        groups.append(
            Group(
                cfg,
                prepared[members[0]][3],
                jax.tree.map(stack, *inps),
                jnp.stack(lps),
                jnp.stack(truths),
                tuple(members),
                grid_span_m(cfg),
            )
        )
    return groups, group_of


def run_metrics(
    cfg: pgp.FilterConfig,
    prm: pgp.FilterParams,
    inp: pgp.FilterInputs,
    logpost0,
    truth,
    span_m: float,
) -> dict[str, Float[Array, ""]]:
    """Run the filter once and reduce it to the sweep's metrics (one run; `run_batch` vmaps it)."""
    _, out = pgp.run_filter(cfg, prm, inp, logpost0)
    return reduce_metrics(out, prm, truth, span_m)


def reduce_metrics(out: pgp.FilterOut, prm: pgp.FilterParams, truth, span_m: float) -> dict[str, Float[Array, ""]]:
    """The sweep's metrics (`METRICS`) of one run's per-epoch outputs."""
    est = out.estimate
    have = jnp.isfinite(est).all(-1)[:, 1:]
    return {
        "rmse_m": track_rmse(est, truth),
        "final_rmse_m": final_rmse(est, truth),
        "availability": jnp.mean(have.astype(est.dtype)),
        "localised": jnp.sum(have[-1]).astype(est.dtype),
        "nlpl": neg_log_predictive(out, prm.sigma_r, prm.p_out, span_m),
    }


def _batched(cfg, prm, inp, logpost0, truth, span_m):
    return jax.vmap(run_metrics, in_axes=(None, 0, 0, 0, 0, None))(cfg, prm, inp, logpost0, truth, span_m)


# One compilation per (group config, batch shape): parameter values and datasets are array data.
run_batch = eqx.filter_jit(_batched)
_reduce_batch = eqx.filter_jit(jax.vmap(reduce_metrics, in_axes=(0, 0, 0, None)))


def run_batch_window(cfg, prm, inp, logpost0, truth, span_m) -> dict[str, Array]:
    """`run_batch` on the windowed fast path (`mesh.lockstep`): the host decides each step's
    branch for the whole batch, so runs pay the full-grid epoch only when one of them needs it."""
    from jaxcal.mesh.lockstep import run_lockstep

    out = run_lockstep(cfg, prm, inp, logpost0)
    return _reduce_batch(out, prm, truth, span_m)


_reduce_jit = eqx.filter_jit(reduce_metrics)


def run_single(
    cfg: pgp.FilterConfig,
    prm: pgp.FilterParams,
    inp: pgp.FilterInputs,
    logpost0,
    truth,
    span_m: float,
) -> dict[str, Array]:
    """One run exactly as `pgp.run_pgp` runs it (`pgp.run_chunked`, the fast path), reduced to
    the metrics: the "sequential" execution. Compiles once per group config (chunk programs of
    `run_chunked` and `reduce_metrics`), not per parameter value."""
    _, out = pgp.run_chunked(cfg, prm, inp, logpost0)
    return _reduce_jit(out, prm, truth, span_m)


def _shard(tree, mesh):
    """Put a host pytree with a leading batch axis on the devices of `mesh`, sharded along it."""
    from jax.sharding import NamedSharding, PartitionSpec

    sh = NamedSharding(mesh, PartitionSpec("runs"))
    if jax.process_count() == 1:
        return jax.device_put(tree, sh)
    return jax.tree.map(lambda a: jax.make_array_from_callback(a.shape, sh, lambda idx: a[idx]), tree)


def _gather(tree) -> dict:
    if jax.process_count() == 1:
        return jax.tree.map(np.asarray, tree)
    from jax.experimental import multihost_utils

    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def execute(
    spec: SweepSpec,
    pl: Plan,
    groups: Sequence[Group | LocalGroup],
    group_of: np.ndarray,
    done: np.ndarray,
    devices: Sequence | None = None,
    progress: Callable[[int], None] | None = None,
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Run every run not yet `done`, batch by batch.

    Batches are fixed chunks of each group's runs (an interrupted sweep rebuilds the same batches);
    a chunk whose runs are all done is skipped, and only its runs not done are computed.

    Args:
        spec, pl, groups, group_of: from `parse_spec`, `plan`, `build_groups`.
        done: (R,) bool, runs already finished.
        devices: devices of the 1-D mesh (default `jax.devices()`, all processes).
        progress: optional callback called with the number of runs finished since its last call
            (after each run of this process's devices with "sequential", after each batch with
            "vmap").

    Yields:
        (run indices, metrics name -> values) per finished batch.
    """
    from jax.sharding import Mesh

    devs = list(devices) if devices is not None else jax.devices()
    mesh = Mesh(np.asarray(devs), ("runs",))
    execution = resolve_execution(spec.execution, devs[0].platform)
    # per-device width fixed by the spec: every device runs the same program whatever their number
    bsz = spec.batch_size * len(devs)
    run_group = group_of[pl.dataset_of]
    for gi, g in enumerate(groups):
        runs = np.flatnonzero(run_group == gi)
        if isinstance(g, LocalGroup):
            yield from _run_local(spec, pl, g, runs[~done[runs]], progress)
            continue
        local = {d: k for k, d in enumerate(g.members)}
        dtype = np.asarray(g.base.sigma_r).dtype
        inp_np = jax.tree.map(np.asarray, g.inp)
        lp0_np, truth_np = np.asarray(g.logpost0), np.asarray(g.truth)
        for start in range(0, runs.size, bsz):
            chunk = runs[start : start + bsz]
            todo = chunk[~done[chunk]]
            if todo.size == 0:
                continue
            padded = np.concatenate([todo, np.repeat(todo[-1:], bsz - todo.size)])
            ds_idx = np.asarray([local[int(pl.dataset_of[r])] for r in padded])
            prm = g.base
            for name, vals in pl.values.items():
                prm = dataclasses.replace(prm, **{name: vals[padded]})
            prm = jax.tree.map(lambda a, t=dtype: np.broadcast_to(np.asarray(a, t), (bsz,)), prm)
            host = (
                prm,
                jax.tree.map(lambda a, i=ds_idx: a[i], inp_np),
                lp0_np[ds_idx],
                truth_np[ds_idx],
            )
            if execution == "sequential":
                out = _gather(_run_sequential(g, host, todo.size, mesh, spec.batch_size, progress))
            elif g.cfg.window and not g.cfg.n_snap:  # lockstep chunks, one driver per device
                out = _gather(_run_lockstep(g, host, mesh, spec.batch_size))
            else:  # the one-scan likelihoods: one vmapped scan (both branches of every cond)
                out = _gather(run_batch(g.cfg, *_shard(host, mesh), g.span_m))  # type: ignore[call-arg]
                if progress is not None:
                    progress(int(todo.size))
            yield todo, {k: np.asarray(v, np.float64)[: todo.size] for k, v in out.items()}
        release_if_crowded()  # many groups (grid shapes) compile many programs: stay below the map limit


def _run_local(spec: SweepSpec, pl: Plan, g: LocalGroup, todo: np.ndarray, progress):
    """The runs of a `LocalGroup`, one `local_metrics` each, yielded one by one."""
    where = {d: k for k, d in enumerate(g.members)}
    for r in todo:
        ds, config = g.datasets[where[int(pl.dataset_of[r])]]
        values: dict[str, Any] = {k: float(v[r]) for k, v in pl.values.items()}
        params = dataclasses.replace(g.params, **values)
        m = local_metrics(ds, config, params, spec.method)
        if progress is not None:
            progress(1)
        yield np.asarray([r]), {k: np.asarray([m[k]], np.float64) for k in METRICS}


def _per_device(mesh, per: int, work) -> dict:
    """`work(j, device)` -> metrics (per,) for each of this process's devices (one thread each
    when several), assembled as arrays sharded like the batch (row i on device i // per)."""
    from jax.sharding import NamedSharding, PartitionSpec

    devs = list(mesh.devices.flat)
    mine = [(j, d) for j, d in enumerate(devs) if d.process_index == jax.process_index()]
    if len(mine) == 1:
        parts = [work(*mine[0])]
    else:  # the runtime releases the GIL while a device computes
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(len(mine)) as pool:
            parts = list(pool.map(lambda jd: work(*jd), mine))
    if jax.process_count() == 1:
        return {k: np.concatenate([p[k] for p in parts]) for k in METRICS}
    sh = NamedSharding(mesh, PartitionSpec("runs"))
    shape = (per * len(devs),)
    return {
        k: jax.make_array_from_single_device_arrays(
            shape, sh, [jax.device_put(p[k], d) for p, (_, d) in zip(parts, mine, strict=True)]
        )
        for k in METRICS
    }


def _run_lockstep(g: Group, host, mesh, per: int) -> dict:
    """The "vmap" execution on the windowed fast path: each of this process's devices runs its
    `per` rows as one vmapped lockstep batch (`run_batch_window`)."""

    def work(j, dev):
        rows = jax.device_put(jax.tree.map(lambda a: a[j * per : (j + 1) * per], host), dev)
        m = run_batch_window(g.cfg, *rows, g.span_m)
        return {k: np.asarray(m[k]) for k in METRICS}

    return _per_device(mesh, per, work)


def _run_sequential(g: Group, host, n_real: int, mesh, per: int, progress) -> dict:
    """The "sequential" execution of one batch: each of this process's devices runs its rows
    (`per` of them, row i on device i // per) one by one with `run_single`; rows past `n_real`
    (padding) are not run (NaN)."""
    dtype = host[2].dtype

    def work(j, dev):
        vals = {k: np.full(per, np.nan, dtype) for k in METRICS}
        with jax.default_device(dev):
            for i in range(j * per, min((j + 1) * per, n_real)):
                row = jax.device_put(jax.tree.map(lambda a, i=i: a[i], host), dev)
                m = run_single(g.cfg, *row, g.span_m)
                for k in METRICS:
                    vals[k][i - j * per] = np.asarray(m[k])
                if progress is not None:
                    progress(1)
        return vals

    return _per_device(mesh, per, work)


def simulate_or_raise(sc: Scenario, seed: int) -> MeshDataset:
    """The dataset of a `simulate` scenario and seed (overrides passed to `sim.mesh.simulate`)."""
    from jaxcal.sim.mesh import simulate

    if sc.simulate is None:
        raise JaxcalError("sweep spec: a scenario without `simulate` reads a file")
    return simulate(sc.simulate, seed, **dict(sc.overrides))
