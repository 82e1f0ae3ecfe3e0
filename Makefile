# Two entry points on a fresh machine (see README.md):
#   make sim    the main job: the daemon against the simulated rig (installs slipd with its `sim` extra)
#   make test   the test suite (installs the `train` and `dev` extras, torch included; what .ci/run runs,
#               followed by `make wheel-test`)
# Both create .venv on first use; `make test` adds its extras to a venv that `make sim` made.
#
# torch: `make test` installs torch==2.13.0. On a machine without a local CPU build, pip would fetch the
# default build, which pulls several GB of CUDA packages; point pip at PyTorch's CPU wheels instead:
#   make test TORCH_INDEX=https://download.pytorch.org/whl/cpu
# Left unset (the default), pip uses its usual indexes only.
PY ?= python3
VENV ?= .venv
TORCH_INDEX ?=
BIN := $(VENV)/bin
SIM_STAMP := $(VENV)/.installed-sim
TEST_STAMP := $(VENV)/.installed-test
WHEEL_TEST := out/wheel-test
TORCH_PIP_ARGS := $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX))

.PHONY: sim test lint install wheel-test sample config-reference

$(BIN)/python:
	@echo "== creating $(VENV) (a few seconds)"
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

# The simulator's set-up: slipd, numpy, onnxruntime, the device libraries, scipy, matplotlib (a .venv of
# about 450 MB; 40 s the first time with the wheels at hand, longer when pip downloads them).
$(SIM_STAMP): pyproject.toml | $(BIN)/python
	@echo "== installing slipd with the sim extra into $(VENV) (about 450 MB; under a minute to a few minutes)"
	$(BIN)/pip install --progress-bar off -e '.[sim]'
	touch $@

# The test suite's set-up: the above plus torch (CPU build), onnx, pytest, ruff, mypy (a .venv of about
# 1.5 GB; a few minutes the first time). It includes everything `make sim` needs, so it stamps both.
$(TEST_STAMP): pyproject.toml | $(BIN)/python
	@echo "== installing slipd with the train and dev extras into $(VENV) (torch included, about 1.5 GB; a few minutes)"
	$(BIN)/pip install --progress-bar off $(TORCH_PIP_ARGS) -e '.[train,dev]'
	touch $@ $(SIM_STAMP)

install: $(TEST_STAMP)

sim: $(SIM_STAMP)
	$(BIN)/slipd sim $(ARGS)

test: $(TEST_STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q $(ARGS)

lint: $(TEST_STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

# What a robot's computer gets from `pip install slipd`: build the wheel from the files git knows
# (a copy, so stale build/ output or a local egg-info cannot leak into it), install it into a fresh
# virtual environment WITHOUT extras, run the daemon's commands from outside the checkout (so
# `import slipd` is the installed one), and check that none of the extras came along: `slipd sim` and
# `import sliplab` must say in one line which extra they need, and the pages the systemd unit names must be
# installed. The fresh venv gets no pip of its own: the dev venv's pip installs into it (`pip --python`),
# which saves bootstrapping one.
wheel-test: $(TEST_STAMP)
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
	  venv/bin/slipd replay --sample && \
	  test -f venv/share/doc/slipd/install.md && \
	  { venv/bin/slipd sim 2>sim.err; test $$? -eq 2; } && test "$$(wc -l <sim.err)" -eq 1 && \
	  grep -q "install slipd\[sim\]" sim.err && \
	  { ! venv/bin/python -c "import sliplab" 2>lab.err; } && grep -q "needs the train extra" lab.err && \
	  venv/bin/python -c "import slipd.cli, slipd.daemon.service, slipd.daemon.loop, slipd.detect.replay" && \
	  venv/bin/python -c "import importlib.util as u; \
	    extra = [m for m in ['torch', 'scipy', 'matplotlib', 'tqdm', 'mujoco'] if u.find_spec(m) is not None]; \
	    assert not extra, f'installed without extras, yet present: {extra}'"
	@echo "wheel-test: OK ($$(ls $(WHEEL_TEST)/dist))"

# The packaged sample recording (slipd/models/sample_slip.npz): the shipped hexapod translation scene,
# cut to 1.5 s (onset at 1.038 s, gross slip at 1.346 s), seed 0. Deterministic: tests/test_packaging.py
# regenerates it and compares.
sample: $(TEST_STAMP)
	$(BIN)/python -c "from slipd.sim.scene import load_scene, parse_scene, generate; \
	  sc = load_scene('slipd/sim/scenes/hexapod_translation.yaml'); \
	  sc = parse_scene({**sc.model_dump(mode='json'), 'duration_s': 1.5}, 'sample'); \
	  generate(sc, seed=0).save('slipd/models/sample_slip.npz')"

# docs/configuration.md from the schema's field descriptions (tests/test_docs.py fails when it is stale).
config-reference: $(TEST_STAMP)
	$(BIN)/python tools/config_reference.py --out docs/configuration.md
