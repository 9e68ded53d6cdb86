# splitbench: a new user needs only `make reproduce` and `make test`; both do the set-up.
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
PYTEST_ARGS ?=
# Scene files the project does not ship (Dabrovic Sponza) are found on SPLITBENCH_SCENE_PATH (docs/scenes.md); a
# shared scenes folder beside the checkout joins it when it exists. Without it those scenes are unavailable.
SHARED_SCENES := $(abspath ../shared/scenes)
ifneq ($(wildcard $(SHARED_SCENES)),)
export SPLITBENCH_SCENE_PATH := $(if $(SPLITBENCH_SCENE_PATH),$(SPLITBENCH_SCENE_PATH):)$(SHARED_SCENES)
endif

.PHONY: setup test smoke reproduce report bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh

test: $(STAMP)
	$(PY) -m pytest -q $(PYTEST_ARGS)

smoke: $(STAMP)
	$(VENV)/bin/splitbench reproduce --preset smoke

# The quick preset (each method's own grid), the shared cross-method matrix (suite/harness/compare.toml, timed by
# the work clock, so the two worker processes' runs do not skew each other's times), the method benchmarks whose
# figures the report sections show, the rendering core's benchmarks on every backend that works here (a GPU
# included), then the report.
COMPARE_WORKERS ?= 2
reproduce: $(STAMP)
	$(VENV)/bin/splitbench reproduce --preset quick --no-report
	$(VENV)/bin/splitbench reproduce --preset compare --executor processes --workers $(COMPARE_WORKERS) --no-report
	$(VENV)/bin/splitbench bench visibility_bitmap
	$(VENV)/bin/splitbench bench quake_drt
	$(VENV)/bin/splitbench bench rail
	$(VENV)/bin/splitbench bench layered_pvs
	$(VENV)/bin/splitbench bench core --backend all
	$(VENV)/bin/splitbench bench tracing --scene all --backend all --out results
	$(VENV)/bin/splitbench report

report: $(STAMP)
	$(VENV)/bin/splitbench report

bench: $(STAMP)
	$(VENV)/bin/splitbench bench tracing

clean:
	rm -rf results report build *.egg-info
