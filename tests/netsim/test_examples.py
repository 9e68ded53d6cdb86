"""Every component's runnable example runs (python -m netsim.<module>)."""

import runpy

import pytest


@pytest.mark.filterwarnings("ignore:.*found in sys.modules:RuntimeWarning")
@pytest.mark.parametrize("module", ["netsim.env", "netsim.link", "netsim.tcp", "netsim.udp", "netsim.topology"])
def test_component_example_runs(module, capsys):
    runpy.run_module(module, run_name="__main__")
    assert capsys.readouterr().out.strip()
