"""Sweeps give the same results (counters, bytes, images) whichever executor runs them."""
import pandas as pd
import pytest

from suite.harness import executor
from suite.errors import UserError


def _table(outcomes):
    rows = []
    for out in outcomes:
        assert out["error"] is None, out
        df = pd.read_parquet(f"{out['run_dir']}/frames.parquet")
        df["net"] = out["config"]["net"]
        rows.append(df[["net", "frame", "rays", "bytes_up", "bytes_down", "image_sha256"]])
    return pd.concat(rows, ignore_index=True)


def _configs(fake_config):
    return [fake_config(net=net, seed=3) for net in ("ideal", "bw=8mbps,delay=5ms")] + \
        [fake_config("synthetic_async", net="bw=8mbps,delay=5ms", frames=4, clock="work")]


def test01_dask_local_cluster_sweep_matches_the_serial_sweep(fake_config, tmp_path):
    configs = _configs(fake_config)
    serial = executor.sweep(configs, tmp_path / "serial")
    # processes=False keeps the test's stand-in core (monkeypatched hooks) visible to the two workers
    with executor.make_executor("dask", workers=2, processes=False) as ex:
        assert len(ex.client.scheduler_info()["workers"]) == 2
        dask = executor.sweep(configs, tmp_path / "dask", ex)
    pd.testing.assert_frame_equal(_table(serial), _table(dask))


def test02_a_failing_run_is_reported_and_the_sweep_goes_on(fake_config, fake_core, tmp_path, monkeypatch):
    configs = _configs(fake_config)[:2]
    real = fake_core.make_network

    def broken_for_delayed(net, clients, server_net, seed):
        if net != "ideal":
            raise RuntimeError("link exploded")
        return real(net, clients, server_net, seed)

    monkeypatch.setattr(fake_core, "make_network", broken_for_delayed)
    outcomes = executor.sweep(configs, tmp_path)
    assert outcomes[0]["error"] is None and "link exploded" in outcomes[1]["error"]


def test03_unknown_executor_is_a_user_error():
    with pytest.raises(UserError, match="unknown executor 'cloud'"):
        executor.make_executor("cloud")


def test04_process_executor_returns_every_result():
    import operator

    with executor.make_executor("processes", workers=2) as ex:
        assert sorted(ex.map(operator.neg, [1, 2, 3])) == [-3, -2, -1]
