# Two entry points on a fresh machine (see README.md):
#   make sim    the main job: the daemon against the simulated rig
#   make test   the test suite (what .ci/run runs, followed by `make wheel-test`)
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
WHEEL_TEST := out/wheel-test

.PHONY: sim test lint install wheel-test sample config-reference

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[train,dev]'
	touch $(STAMP)

install: $(STAMP)

sim: $(STAMP)
	$(BIN)/slipd sim $(ARGS)

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

# What a robot's computer gets from `pip install slipd`: build the wheel from the files git knows
# (a copy, so stale build/ output or a local egg-info cannot leak into it), install it into a fresh
# virtual environment WITHOUT extras, run the daemon's commands from outside the checkout (so
# `import slipd` is the installed one), and check that none of the extras came along. The fresh venv gets
# no pip of its own: the dev venv's pip installs into it (`pip --python`), which saves bootstrapping one.
wheel-test: $(STAMP)
	rm -rf $(WHEEL_TEST) && mkdir -p $(WHEEL_TEST)/src
	git ls-files -z --cached --others --exclude-standard \
	  | tar --null --ignore-failed-read -cf - -T - 2>/dev/null | tar -xf - -C $(WHEEL_TEST)/src
	$(BIN)/python -m build --wheel --no-isolation --outdir $(WHEEL_TEST)/dist $(WHEEL_TEST)/src >/dev/null
	$(PY) -m venv --without-pip $(WHEEL_TEST)/venv
	$(BIN)/pip --python $(WHEEL_TEST)/venv/bin/python install --quiet --no-compile $(WHEEL_TEST)/dist/slipd-*.whl
	cd $(WHEEL_TEST) && set -e && \
	  venv/bin/python -c "import slipd, sys; assert '/venv/' in slipd.__file__, slipd.__file__" && \
	  venv/bin/slipd version && \
	  venv/bin/slipd check-config $(CURDIR)/config/slipd.yaml && \
	  venv/bin/slipd models && \
	  venv/bin/slipd replay "$$(venv/bin/python -c 'from slipd.models import SAMPLE_RECORDING as s; print(s)')" && \
	  venv/bin/python -c "import slipd.cli, slipd.daemon.service, slipd.daemon.loop, slipd.detect.replay" && \
	  venv/bin/python -c "import importlib.util as u; \
	    extra = [m for m in ['torch', 'scipy', 'matplotlib', 'tqdm'] if u.find_spec(m) is not None]; \
	    assert not extra, f'installed without extras, yet present: {extra}'"
	@echo "wheel-test: OK ($$(ls $(WHEEL_TEST)/dist))"

# The packaged sample recording (slipd/models/sample_slip.npz): the shipped hexapod translation scene,
# cut to 1.5 s (onset at 1.038 s, gross slip at 1.346 s), seed 0. Deterministic: tests/test_packaging.py
# regenerates it and compares.
sample: $(STAMP)
	$(BIN)/python -c "from slipd.sim.scene import load_scene, parse_scene, generate; \
	  sc = load_scene('config/scenes/hexapod_translation.yaml'); \
	  sc = parse_scene({**sc.model_dump(mode='json'), 'duration_s': 1.5}, 'sample'); \
	  generate(sc, seed=0).save('slipd/models/sample_slip.npz')"

# docs/configuration.md from the schema's field descriptions (tests/test_docs.py fails when it is stale).
config-reference: $(STAMP)
	$(BIN)/python tools/config_reference.py --out docs/configuration.md
