"""``splitbench reproduce --scheduler tcp://HOST:PORT`` on a real Dask cluster: a ``dask scheduler`` and two
``dask worker`` processes started on localhost (not an in-process LocalCluster), running the synthetic methods
(their core comes from the worker preload tests/harness/dask_fake_core.py)."""
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from suite.harness import cli, executor, presets, results

HERE = Path(__file__).parent
DASK = Path(sys.executable).with_name("dask")
METHODS = "synthetic_sync,synthetic_async"
TINY = HERE / "compare_tiny.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def cluster(fake_core, tmp_path):
    """A scheduler and two single-threaded workers as separate processes; yields the scheduler address."""
    if not DASK.exists():
        pytest.skip("the dask command line is not installed")
    env = dict(os.environ, SPLITBENCH_METHOD_PATHS=str(HERE / "fake_methods"), SPLITBENCH_PROGRESS="0")
    address = f"tcp://127.0.0.1:{_free_port()}"
    logs = [open(tmp_path / f"dask{k}.log", "w") for k in range(3)]
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--no-dashboard"], env=env, stdout=logs[0], stderr=subprocess.STDOUT)]
    procs += [subprocess.Popen([str(DASK), "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                "--preload", str(HERE / "dask_fake_core.py"), "--name", f"w{k}"],
                               env=env, stdout=logs[k], stderr=subprocess.STDOUT, cwd=tmp_path) for k in (1, 2)]
    try:
        from dask.distributed import Client

        deadline = time.monotonic() + 20
        while True:
            try:
                with Client(address, timeout="2s") as client:
                    client.wait_for_workers(2, timeout=max(1.0, deadline - time.monotonic()))
                break
            except (OSError, TimeoutError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.3)
        yield address
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=3)
            except subprocess.TimeoutExpired:
                proc.kill()
        for log in logs:
            log.close()


def _wait_until_idle(address: str, out_root: Path, timeout_s: float = 20.0) -> None:
    """Until no worker executes a task and no run is being written (``.tmp-*`` directories)."""
    from dask.distributed import Client

    deadline = time.monotonic() + timeout_s
    with Client(address, timeout="5s") as client:
        while time.monotonic() < deadline:
            busy = client.run(lambda dask_worker: dask_worker.state.executing_count)
            if not any(busy.values()) and not list(out_root.glob(".tmp-*")):
                return
            time.sleep(0.1)
    raise TimeoutError("the cluster did not become idle")


def _frames(out_root) -> pd.DataFrame:
    rows = []
    for run_dir in results.complete_runs(out_root):
        df = pd.read_parquet(run_dir / "frames.parquet")
        df["run"] = run_dir.name
        rows.append(df[["run", "frame", "rays", "bytes_up", "bytes_down", "image_sha256", "dssim", "rel_mse"]])
    return pd.concat(rows, ignore_index=True).sort_values(["run", "frame"]).reset_index(drop=True)


def _stamps(out_root) -> dict:
    return {d.name: (d / "summary.json").stat().st_mtime_ns for d in results.complete_runs(out_root)}


def test_an_interrupted_sweep_on_a_real_cluster_resumes_without_recomputing_and_matches_serial(
        cluster, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(presets, "scene_available", lambda scene: scene == "toy")
    configs, problems, record = presets.expand("compare", methods=METHODS, matrix_file=TINY)
    assert len(configs) == 12 and not problems and record["skipped_scenes"] == ["missing_scene"]
    serial = executor.sweep(configs, tmp_path / "serial")
    assert all(o["error"] is None for o in serial)
    reproduce = ["reproduce", "--preset", "compare", "--matrix", str(TINY), "--methods", METHODS,
                 "--scheduler", cluster, "--out", str(tmp_path / "dask"), "--no-report"]

    # The first sweep is interrupted after three runs came back (Ctrl-C in the middle of the sweep); the runs in
    # flight on the two workers may still finish, the queued ones are dropped with the client.
    real_map = executor.DaskExecutor.map

    def interrupted_map(self, fn, items, *args):
        for k, out in enumerate(real_map(self, fn, items, *args)):
            if k == 3:
                raise KeyboardInterrupt
            yield out

    monkeypatch.setattr(executor.DaskExecutor, "map", interrupted_map)
    assert cli.main(reproduce) == 130
    monkeypatch.setattr(executor.DaskExecutor, "map", real_map)
    _wait_until_idle(cluster, tmp_path / "dask")  # the runs that were in flight finish writing
    finished = _stamps(tmp_path / "dask")
    assert 3 <= len(finished) < len(configs)

    capsys.readouterr()
    assert cli.main(reproduce + ["--json"]) == 0
    outcome = json.loads(capsys.readouterr().out)
    skipped = {Path(r["run_dir"]).name for r in outcome["runs"] if r["skipped"]}
    # finished runs were skipped, and not recomputed: their files are the ones the interrupted sweep wrote
    assert skipped == set(finished)
    after = _stamps(tmp_path / "dask")
    assert {name: after[name] for name in finished} == finished and len(after) == len(configs)
    # the resumed distributed sweep gives what the serial executor gives (counters, bytes, images, metrics)
    pd.testing.assert_frame_equal(_frames(tmp_path / "serial"), _frames(tmp_path / "dask"))
    stored = json.loads((tmp_path / "dask" / "presets" / "compare.json").read_text())
    assert stored["executor"] == "dask" and stored["scheduler"] == cluster
    assert stored["skipped_scenes"] == ["missing_scene"] and stored["already_complete"] == len(finished)
