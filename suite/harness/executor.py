"""Executors for sweeps (``reproduce``, grids): serial, local processes, or Dask distributed.

Every executor maps one function over run configs and yields results as they complete. The unit of work is
:func:`run_one`: it executes one config into the results store and returns a small JSON-able dict, so a run
that already completed elsewhere is skipped wherever it lands. Results are identical whichever executor ran
them (counters, bytes, images); only measured times differ.
"""
from __future__ import annotations

import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

from suite.errors import UserError
from suite.progress import progress

EXECUTORS = ("serial", "processes", "dask")


def run_one(cfg: dict, results_root: str, force: bool = False) -> dict:
    """Runs one config; failures come back as data so that one broken run does not stop a sweep."""
    from suite.harness import runner

    try:
        out = runner.execute(cfg, results_root, force=force)
        return {"config": cfg, "run_dir": out["run_dir"], "skipped": out["skipped"], "error": None,
                "wall_s": out["summary"].get("run_wall_s", {}).get("total", 0.0)}
    except UserError as exc:
        return {"config": cfg, "run_dir": None, "skipped": False, "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - reported per run, with its traceback tail
        tail = traceback.format_exc().strip().splitlines()[-3:]
        return {"config": cfg, "run_dir": None, "skipped": False, "error": f"{type(exc).__name__}: {exc}",
                "traceback": tail}


class SerialExecutor:
    name = "serial"

    def map(self, fn, items, *args):
        for item in items:
            yield fn(item, *args)

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class ProcessExecutor(SerialExecutor):
    """Local worker processes (spawned, so Dr.Jit / Embree threads are never forked)."""

    name = "processes"

    def __init__(self, workers: int = 2):
        self.pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))

    def map(self, fn, items, *args):
        futures = [self.pool.submit(fn, item, *args) for item in items]
        for fut in as_completed(futures):
            yield fut.result()

    def close(self):
        self.pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(SerialExecutor):
    """Dask distributed: a LocalCluster by default, or an existing scheduler (``tcp://host:port``)."""

    name = "dask"

    def __init__(self, scheduler: str | None = None, workers: int = 2, processes: bool = True):
        from dask.distributed import Client, LocalCluster

        self.cluster = None
        if scheduler:
            try:
                self.client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise UserError(f"cannot reach Dask scheduler '{scheduler}' ({exc})") from None
        else:
            # One thread per worker: each run is one benchmark process and must not share cores with another.
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=processes,
                                        dashboard_address=None)
            self.client = Client(self.cluster)

    def map(self, fn, items, *args):
        from dask.distributed import as_completed as dask_completed

        items = list(items)
        # pure=False: a rerun must be executed (it is skipped by the results store, not by Dask's cache)
        futures = [self.client.submit(fn, item, *args, pure=False) for item in items]
        for fut in dask_completed(futures):
            yield fut.result()

    def close(self):
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def make_executor(kind: str = "serial", scheduler: str | None = None, workers: int = 2, processes: bool = True):
    if scheduler:
        kind = "dask"
    if kind not in EXECUTORS:
        raise UserError(f"unknown executor '{kind}' (choose from {', '.join(EXECUTORS)})")
    if workers < 1:
        raise UserError(f"worker count must be >= 1, got {workers}")
    if kind == "serial":
        return SerialExecutor()
    if kind == "processes":
        return ProcessExecutor(workers)
    return DaskExecutor(scheduler, workers, processes)


def sweep(configs: list[dict], results_root, executor=None, desc: str = "runs", force: bool = False) -> list[dict]:
    """Runs every config through ``executor`` (serial by default); returns the outcomes in config order.
    ``force`` recomputes runs that are already complete."""
    executor = executor or SerialExecutor()
    outcomes = [None] * len(configs)
    # Executors yield in completion order; the index restores config order.
    keyed = [dict(c, _sweep_index=i) for i, c in enumerate(configs)]
    for out in progress(executor.map(_indexed_run, keyed, str(results_root), bool(force)), total=len(configs), desc=desc,
                        unit="run"):
        outcomes[out.pop("sweep_index")] = out
    return outcomes


def _indexed_run(cfg: dict, results_root: str, force: bool = False) -> dict:
    cfg = dict(cfg)
    index = cfg.pop("_sweep_index")
    out = run_one(cfg, results_root, force)
    out["sweep_index"] = index
    return out
