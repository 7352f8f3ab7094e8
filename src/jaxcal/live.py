"""Live calibration while recording: `jaxcal record ... --calibrate pgp`.

The recorder calls `LiveCalibrator.update(rec)` at each flush (live: every second; replay: every
second of frame time) and `update(rec, final=True)` at the end. Design:

* **Epochs**: the same mapping as `Recording._mesh` (windows of ``epoch_s`` from the first range,
  range = mean of the window's i->j measurements, epoch time = mean time of its ranges), formed
  incrementally: an epoch is *closed* once a range of a later window has arrived (frame times never go
  back, see `recorder`); closed epochs are kept sparse (pairs, means) in a bounded buffer.
* **Startup rule**: the filter needs the node set and a grid extent. Epochs are buffered until three
  nodes (the frame a0, a1, a2) have ranged each other (every one of the three pairs) in at least
  ``min_epochs`` (20) epochs. a0, a1, a2 are the first three such nodes in id order (numeric when all
  ids are numbers), or the ``--config`` ids. The filter then starts over every node seen so far, its
  grid half-width sized from the buffered epochs' median ranges (`grid.extent_radius`, as the batch
  method does from the whole recording), and the buffer is fed to it.
* **New node**: when a closed epoch carries a node the running filter does not know, the filter is
  restarted over all nodes from the buffered epochs (grid re-sized, same frame). The buffer holds the
  last ``buffer_epochs`` (default 3,000: 5 min of 0.1 s epochs; while it is re-fed, the recorder's
  reader thread keeps queueing bytes); when older
  epochs were dropped, their estimates stay those of the previous run (the new node NaN there), and
  the final result can differ from a batch run, which sees every epoch.
* **Chunks**: at each flush the closed epochs go to `pgp.advance` in chunks of exactly ``chunk``
  epochs (a shorter rest waits for the next flush; at the end it goes one epoch at a time). Default
  ``chunk = 1``: a single compiled shape (compiling a shape costs seconds, far more than the
  per-call overhead chunks would save: timings on the benchmarks page), so there is no second
  compilation at the end. Chunking does not change the answer
  (`advance` carries the whole filter state).
* **Settled**: a node is settled when it is localised and its estimate moved less than one grid cell
  (``cell_m``) over the last ``settle_epochs`` (10) epochs (max distance of those estimates from the
  newest one). The table also shows sd = sqrt(trace of the posterior covariance) [m].

Without restarts, and when the buffered epochs size the grid like the whole recording does, the live
result equals a batch `jaxcal calibrate --method pgp` on the recorded file (which holds the live frame as
its ``default`` configuration); a different grid extent changes the answers by at most about a cell.
"""

from __future__ import annotations

import math
import re
import sys
from collections import deque
from typing import Any

import numpy as np

__all__ = ["LiveCalibrator", "frame_ids"]


def _id_key(ids):
    """Natural order: digit runs compare as numbers (N2 < N10, 2 < 10)."""

    def key(s):
        return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"(\d+)", str(s)) if p)

    return key


def frame_ids(pair_epochs: dict, ids: list[str], min_epochs: int, wanted=None):
    """The frame (a0, a1, a2) ids: `wanted` or the first triple in id order whose three pairs each
    have ranges in >= `min_epochs` epochs; None while there is none.

    Args:
        pair_epochs: {(i, j) with i < j: number of epochs with a range between nodes i and j} (indices).
        ids: node ids, index order. min_epochs: epochs required per pair. wanted: 3 ids or None.
    """
    idx = {s: k for k, s in enumerate(ids)}

    def ok(a, b):
        i, j = sorted((idx[a], idx[b]))
        return pair_epochs.get((i, j), 0) >= min_epochs

    if wanted is not None:
        if not all(w in idx for w in wanted):
            return None
        a, b, c = wanted
        return tuple(wanted) if ok(a, b) and ok(a, c) and ok(b, c) else None
    s = sorted(ids, key=_id_key(ids))
    for x in range(len(s)):
        for y in range(x + 1, len(s)):
            if not ok(s[x], s[y]):
                continue
            for z in range(y + 1, len(s)):
                if ok(s[x], s[z]) and ok(s[y], s[z]):
                    return (s[x], s[y], s[z])
    return None


class LiveCalibrator:
    """Runs the PGP filter on a `Recording`'s epochs as they close (see the module docstring).

    Args:
        params: dict of `PGPParams` overrides (None: defaults).
        frame: three node ids (a0, a1, a2) or None (first three by id order).
        min_epochs: epochs each frame pair must have ranged before the filter starts.
        buffer_epochs: closed epochs kept for restarts.
        settle_epochs: N of the settled flag. chunk: epochs per `advance` call.
        stream: where the table goes (None: silent). every_s: table period [s of recording time].
    """

    def __init__(
        self,
        params=None,
        frame=None,
        min_epochs: int = 20,
        buffer_epochs: int = 3000,
        settle_epochs: int = 10,
        chunk: int = 1,
        stream=sys.stderr,
        every_s: float = 5.0,
    ) -> None:
        from jaxcal.mesh.pgp import PGPParams
        from jaxcal.params import with_overrides

        self.params = params if isinstance(params, PGPParams) else with_overrides(PGPParams(), params or {})
        self.wanted = tuple(frame) if frame is not None else None
        self.min_epochs, self.settle_epochs, self.chunk = int(min_epochs), int(settle_epochs), int(chunk)
        self.out, self.every_s = stream, float(every_s)
        self.rows_done = 0
        self.t_first: float | None = None
        self.open_bin: int | None = None
        self._open: list[tuple] = []  # rows (t, src, dst, range) of the open window
        self.epochs: deque = deque(maxlen=int(buffer_epochs))  # (k, time, src, dst, mean) closed epochs
        self.n_closed = 0
        self.pair_epochs: dict[tuple[int, int], int] = {}
        self.times: list[float] = []  # every closed epoch's time
        self.track: list[np.ndarray] = []  # (N_k, 2) estimate per fed epoch (padded at the end)
        self.ids: list[str] = []
        self.frame: tuple[str, str, str] | None = None
        self.pgp: Any = None  # the filter's stream state (pgp.PGPStream) once started
        self.n = 0
        self.restarts = 0
        self.settled_at: dict[str, float] = {}
        self._last_table = -math.inf
        self.error: str | None = None

    # ------------------------------------------------------------------ epochs from the recording
    def _close(self, rec) -> None:
        rows = self._open
        self._open = []
        t = np.array([r[0] for r in rows])
        src = np.array([r[1] for r in rows], np.int64)
        dst = np.array([r[2] for r in rows], np.int64)
        rng = np.array([r[3] for r in rows])
        keep = src != dst
        ok = np.isfinite(rng) & keep
        n = int(max(src.max(), dst.max())) + 1
        flat = src * n + dst
        s = np.bincount(flat[ok], weights=rng[ok], minlength=n * n)
        m = np.bincount(flat[ok], minlength=n * n)
        pairs = np.flatnonzero(m)
        mean = s[pairs] / m[pairs]
        et = float(np.bincount(np.zeros(t.size, np.int64), weights=t)[0] / t.size)
        i, j = pairs // n, pairs % n
        for a, b in {(min(a, b), max(a, b)) for a, b in zip(i.tolist(), j.tolist(), strict=True)}:
            self.pair_epochs[(a, b)] = self.pair_epochs.get((a, b), 0) + 1
        self.epochs.append((self.n_closed, et, i, j, mean))
        self.times.append(et)
        self.n_closed += 1

    def _ingest(self, rec, final: bool) -> int:
        """Move the recording's new ranges into windows; returns how many epochs closed."""
        c = rec.columns()
        t, src, dst, rng = c["time"], c["src"], c["dst"], c["range"]
        before = self.n_closed
        eps = rec.epoch_s
        for q in range(self.rows_done, t.size):
            if self.t_first is None:
                self.t_first = float(t[q])
            b = int(math.floor((float(t[q]) - self.t_first) / eps + 1e-9))
            if self.open_bin is not None and b > self.open_bin:
                self._close(rec)
            if self.open_bin is None or b > self.open_bin:
                self.open_bin = b
            self._open.append((float(t[q]), int(src[q]), int(dst[q]), float(rng[q])))
        self.rows_done = t.size
        if final and self._open:
            self._close(rec)
        return self.n_closed - before

    def _dense(self, items, n: int) -> np.ndarray:
        z = np.full((len(items), n, n), np.nan)
        for k, (_, _, i, j, mean) in enumerate(items):
            z[k, i, j] = mean
        idx = np.arange(n)
        z[:, idx, idx] = np.nan
        return z

    # --------------------------------------------------------------------------------- filter
    def _feed(self, items, final: bool) -> None:
        """Advance over `items` in chunks of exactly `chunk` epochs; a shorter rest waits for more
        epochs, or, at the end, goes one epoch at a time (two compiled shapes in all)."""
        from jaxcal.mesh import pgp

        k = 0
        while k < len(items):
            size = self.chunk if len(items) - k >= self.chunk else (1 if final else 0)
            if size == 0:
                break
            part = items[k : k + size]
            z = self._dense(part, self.n)
            t = np.array([e[1] for e in part])
            prev = np.array([self.times[e[0] - 1] if e[0] > 0 else e[1] for e in part])
            self.pgp, est = pgp.advance(self.pgp, z, t - prev)
            for e, row in zip(part, est, strict=True):
                while e[0] > len(self.track):  # dropped from the buffer before the filter started
                    self.track.append(np.full((self.n, 2), np.nan))
                if e[0] < len(self.track):
                    self.track[e[0]] = row
                else:
                    self.track.append(row)
            k += size

    def _start(self, rec, final: bool) -> None:
        from jaxcal.mesh import grid as G
        from jaxcal.mesh import pgp

        self.ids = list(rec.ids)
        self.n = len(self.ids)
        assert self.frame is not None  # chosen before the filter starts
        rec.frame_ids = self.frame  # the recorded file's `default` configuration: batch = live frame
        a = [self.ids.index(s) for s in self.frame]
        items = list(self.epochs)
        z = pgp.symmetric_ranges(self._dense(items, self.n))
        radius = G.extent_radius(z, a[0], self.params.margin_m, self.params.extent_m)
        if pgp.local_site(self.params, z, a):  # calibrate would run node-local grids: never run another filter
            raise pgp.global_grid_only("live calibration", "live")
        self.pgp = pgp.start(self.n, self.params, anchors=a, radius_m=radius)
        self.radius = radius
        self._feed(items, final)

    def guarded_update(self, rec, final: bool = False) -> None:
        """`update`, but a failure disables live calibration (kept in `error`) and never stops recording."""
        if self.error is not None:
            return
        try:
            self.update(rec, final)
        except Exception as e:  # noqa: BLE001 - reported in one line at the end; recording goes on
            self.error = f"live calibration stopped: {' '.join(str(e).split()) or type(e).__name__}"
            self._say(self.error)

    def update(self, rec, final: bool = False) -> None:
        """Take the recording's new ranges; start, restart or advance the filter; print the table."""
        if self.error is not None:
            return
        self._ingest(rec, final)
        fed = len(self.track)
        if self.pgp is None:
            if self.frame is None:
                self.frame = frame_ids(self.pair_epochs, list(rec.ids), self.min_epochs, self.wanted)
            if self.frame is not None:
                self._start(rec, final)
                self._say(
                    f"live pgp: started after {self.n_closed} epochs, frame a0,a1,a2 = "
                    f"{','.join(self.frame)}, {self.n} nodes, grid half-width {self.radius:.1f} m"
                )
        else:
            new = [e for e in self.epochs if e[0] >= fed]
            if new and max(int(max(e[2].max(initial=0), e[3].max(initial=0))) for e in new) >= self.n:
                self.restarts += 1
                self._start(rec, final)
                self._say(
                    f"live pgp: restarted with {self.n} nodes from {len(self.epochs)} buffered epochs "
                    f"(new node {self.ids[-1]}), grid half-width {self.radius:.1f} m"
                )
            elif new:
                self._feed(new, final)
        if self.pgp is not None and self.track:
            self._report(final)

    # --------------------------------------------------------------------------------- output
    def estimates(self) -> np.ndarray:
        """(N, 2) newest estimates [m], frame coordinates, node order of the recording."""
        return self._row(self.track[-1])

    def _row(self, x) -> np.ndarray:
        x = np.asarray(x, np.float64)
        return np.concatenate([x, np.full((self.n - x.shape[0], 2), np.nan)]) if x.shape[0] < self.n else x

    def settled(self) -> np.ndarray:
        """(N,) bool: localised and moved less than a cell over the last `settle_epochs` epochs."""
        tr = self.track[-self.settle_epochs :]
        if len(tr) < self.settle_epochs:
            return np.zeros(self.n, bool)
        last = tr[-1]
        d = np.stack([np.hypot(*(self._row(x) - self._row(last)).T) for x in tr])
        with np.errstate(invalid="ignore"):
            return np.isfinite(d).all(axis=0) & (
                np.nanmax(np.where(np.isfinite(d), d, np.inf), axis=0) < self.params.cell_m
            )

    def _mean_cov(self):
        from jaxcal.mesh import pgp

        p = pgp.stream_posterior(self.pgp)
        g = self.pgp.cfg.grid
        ax = (np.arange(2 * g.n_half + 1) - g.n_half) * g.cell_m
        X, Y = np.meshgrid(ax, ax, indexing="ij")
        w = p / p.sum(axis=(1, 2), keepdims=True)
        mx, my = (w * X).sum((1, 2)), (w * Y).sum((1, 2))
        dx, dy = X[None] - mx[:, None, None], Y[None] - my[:, None, None]
        cov = np.stack(
            [
                np.stack([(w * dx * dx).sum((1, 2)), (w * dx * dy).sum((1, 2))], -1),
                np.stack([(w * dx * dy).sum((1, 2)), (w * dy * dy).sum((1, 2))], -1),
            ],
            -2,
        )
        # as `run_pgp` reports it: the grid read as a histogram density (+ cell^2 / 12 per free axis)
        return cov + pgp.cell_variance(g.cell_m, cov.shape[0], tuple(self.ids.index(s) for s in self.frame))

    def _say(self, line: str) -> None:
        if self.out is not None:
            tty = getattr(self.out, "isatty", lambda: False)()
            self.out.write(("\r\x1b[K" if tty else "") + line + "\n")  # clear the recorder's status line
            self.out.flush()

    def _report(self, final: bool) -> None:
        t = self.times[len(self.track) - 1] - (self.times[0] if self.times else 0.0)
        st = self.settled()
        for i in np.flatnonzero(st):
            if self.ids[i] not in self.settled_at:
                self.settled_at[self.ids[i]] = t
                x, y = self.estimates()[i]
                self._say(f"live pgp: node {self.ids[i]} settled at ({x:.2f}, {y:.2f}) m, t = {t:.1f} s")
        if self.out is None or not (final or t - self._last_table >= self.every_s):
            return
        self._last_table = t
        sd = np.sqrt(np.trace(self._mean_cov(), axis1=1, axis2=2))
        est = self.estimates()
        head = "final" if final else f"t = {t:.1f} s"
        lines = [f"live pgp {head}, epoch {len(self.track)}: {int(st.sum())}/{self.n} settled"]
        lines.append(f"  {'node':>6} {'x [m]':>8} {'y [m]':>8} {'sd [m]':>7}  settled")
        for name in sorted(self.ids, key=_id_key(self.ids)):
            k = self.ids.index(name)
            x, y = est[k]
            pos = f"{x:8.2f} {y:8.2f}" if np.isfinite(x) else f"{'-':>8} {'-':>8}"
            lines.append(f"  {name:>6} {pos} {sd[k]:7.2f}  {'yes' if st[k] else 'no'}")
        self._say("\n".join(lines))

    def result(self, dataset):
        """The live result as a contract `Result` (track = every epoch's live estimate).

        Args:
            dataset: the recorded `MeshDataset` (its node ids and epoch times).
        """
        from jaxcal.data import Result
        from jaxcal.errors import JaxcalError
        from jaxcal.mesh.pgp import software_version
        from jaxcal.params import as_dict

        if self.pgp is None:
            need = f"the frame {','.join(self.wanted)}" if self.wanted else "three nodes"
            raise JaxcalError(
                f"the filter never started: {need} did not range each other in "
                f"{self.min_epochs} epochs ({self.n_closed} epochs recorded)"
            )
        if list(dataset.node_ids) != self.ids or len(self.track) != dataset.n_epochs:
            raise JaxcalError("live result does not match the recording (nodes or epochs)")
        track = np.stack([self._row(r) for r in self.track])
        cov = self._mean_cov()
        cov[~np.isfinite(track).all(axis=2).any(axis=0)] = np.nan
        a = [self.ids.index(s) for s in self.frame]
        res = Result(
            ids=list(dataset.node_ids),
            position=track[-1],
            method="pgp",
            dataset=dataset.name,
            frame=f"anchors:{a[0]},{a[1]},{a[2]}",
            params=as_dict(self.params),
            covariance=cov,
            track_time=np.asarray(dataset.time, np.float64),
            track_position=track,
            software=software_version(),
        )
        from jaxcal.mesh.masking import mask_result
        from jaxcal.mesh.pgp import with_pair_covariance

        # as `calibrate --method pgp`: widened to the per-pair systematic errors, and what the ranges
        # cannot fix as NaN rows with one warning line
        return mask_result(with_pair_covariance(res, dataset.range), dataset.range)
